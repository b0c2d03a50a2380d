"""Surrogate model: PCA of displacement fields, MLP from marker displacements, ridge baseline."""

from .model import DeformationModel
from .pca import PCABasis, PCACurve, choose_n_components, fit_pca
from .ridge import RidgeBaseline, fit_ridge, marker_columns

__all__ = ["DeformationModel", "PCABasis", "PCACurve", "choose_n_components", "fit_pca", "RidgeBaseline",
           "fit_ridge", "marker_columns"]
