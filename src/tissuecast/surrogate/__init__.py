"""Surrogate model: PCA of displacement fields, MLP from marker displacements, the baselines and
the trust layer, each a :class:`FieldPredictor` (:mod:`.field_predictor`), composed by
:class:`DeformationModel`."""

from .baselines import RidgePredictor, RigidRegistrationPredictor
from .field_predictor import FieldPredictor
from .fit_stage import fit_stage
from .model import DeformationModel
from .network_predictor import NetworkPredictor
from .pca import PCABasis, PCACurve, choose_n_components, fit_pca
from .ridge import RidgeBaseline, fit_ridge, marker_columns
from .state import ModelState
from .trusted import TrustedPredictor

__all__ = ["DeformationModel", "FieldPredictor", "NetworkPredictor", "RidgePredictor", "RigidRegistrationPredictor",
           "TrustedPredictor", "ModelState", "PCABasis", "PCACurve", "choose_n_components", "fit_pca", "RidgeBaseline",
           "fit_ridge", "marker_columns", "fit_stage"]
