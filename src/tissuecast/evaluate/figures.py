"""Matplotlib figures of the report (PNG files; Agg backend, no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import require

__all__ = ["boxplots", "beta_curve", "pca_curve", "pca_validation_curve", "training_curves", "marker_count_curve",
           "architecture_grid", "pyplot", "save_figure"]

PAPER_BETA = {0.0: 1.181, 0.5: 0.889}  # test-2 mean Offset_max (mm) quoted in the paper
PAPER_MARKER_COUNTS = {3: 2.205, 5: 0.837, 10: 0.485, 20: 0.302}  # test-1 mean Offset_max (mm) per n_d, the paper


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (needs the ``viz`` extra)."""
    mpl = require("matplotlib", "viz", "report figures")
    mpl.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` to ``path`` (PNG, 110 dpi), close it and return ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path


#: method -> (short label, colour) of the report's figures
_STYLE = {"mlp": ("MLP", "tab:blue"), "rigid": ("rigid", "tab:green"), "ridge": ("ridge", "tab:orange"),
          "pca_floor": ("PCA floor", "tab:gray")}


def boxplots(evaluation, path: Path) -> Path:
    """Offset_mean and Offset_max per set: MLP, rigid registration, ridge and the PCA floor."""
    plt = pyplot()
    sets = [s for s in ("valid", "test1", "test2") if s in evaluation.sets]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, (col, label) in zip(axes, ((0, "Offset_mean (mm)"), (1, "Offset_max (mm)"))):
        data, labels, colors = [], [], []
        for s in sets:
            r = evaluation.sets[s]
            for m, (short, c) in _STYLE.items():
                v = r.offsets[m][:, col]
                data.append(v[np.isfinite(v)])
                labels.append(f"{s}\n{short}")
                colors.append(c)
        bp = ax.boxplot(data, patch_artist=True, showfliers=True)
        ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=7)
        for patch, c in zip(bp["boxes"], colors):
            patch.set_facecolor(c)
            patch.set_alpha(0.5)
        if col == 1:
            ax.axhline(1.0, color="k", ls=":", lw=1, label="1 mm")
            ax.legend(loc="upper left", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    return save_figure(fig, path)


def beta_curve(evaluation, path: Path) -> Path:
    """Test-2 mean Offset_max / Offset_mean versus beta for every method, paper points."""
    plt = pyplot()
    b = np.array([x for x, _ in evaluation.by_beta])
    fig, ax = plt.subplots(figsize=(8.5, 4.5))
    for col, ls, name in ((1, "-", "max"), (0, "--", "mean")):
        for m, (short, c) in _STYLE.items():
            ax.plot(b, [np.nanmean(r.offsets[m][:, col]) for _, r in evaluation.by_beta], "o" + ls, ms=4, color=c,
                    label=f"{short} Offset_{name}")
    ax.plot(list(PAPER_BETA), list(PAPER_BETA.values()), "k*", ms=10, label="paper MLP Offset_max")
    ax.set_xlabel("beta (LBO share of the test-2 force field)")
    ax.set_ylabel("mean over samples (mm)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes: no line hidden
    return save_figure(fig, path)


def pca_curve(curve, path: Path) -> Path:
    """Cross-validated PCA reconstruction error versus n_w."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.semilogy(curve.n_components, curve.max_error, "o-", ms=3, label=f"{curve.folds}-fold mean of largest vertex error")
    ax.semilogy(curve.n_components, curve.mean_max_error, "s-", ms=3, label="mean per-sample Offset_max")
    ax.semilogy(curve.n_components, curve.mean_error, "^-", ms=3, label="mean vertex error")
    ax.axhline(curve.threshold, color="k", ls=":", lw=1)
    ax.axvline(curve.chosen, color="tab:red", ls="--", lw=1, label=f"chosen n_w = {curve.chosen} (paper: 27)")
    ax.set_xlabel("number of PCA components n_w")
    ax.set_ylabel("reconstruction error (mm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def pca_validation_curve(curve: dict, chosen: int, path: Path) -> Path:
    """Validation mean Offset_max of the model truncated to n_w components, and of the fields'
    own projection (the PCA floor), versus n_w."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    k = np.asarray(curve["n_components"])
    ax.semilogy(k, curve["model_offset_max"], "o-", ms=3, label="model (network truncated to n_w)")
    ax.semilogy(k, curve["floor_offset_max"], "s-", ms=3, color="tab:gray", label="PCA floor (projection of the true field)")
    ax.axvline(chosen, color="tab:red", ls="--", lw=1, label=f"chosen n_w = {chosen}")
    ax.set_xlabel("number of PCA components n_w")
    ax.set_ylabel("validation mean Offset_max (mm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def training_curves(members: list[dict], path: Path, fallback: list[dict] = ()) -> Path:
    """Validation loss versus epoch of each ensemble member, and (dashed) of the markers-only
    fallback's members where the model reads tracked instruments."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for group, style, name in ((members, "-", "member"), (fallback, "--", "fallback member")):
        for k, m in enumerate(group):
            h = np.array(m.get("valid_history") or [[0, np.nan]], dtype=float)
            ax.semilogy(h[:, 0], h[:, 1], style, label=f"{name} {k} (best epoch {m['best_epoch']}, {m['seconds']:.1f} s)")
    ax.set_xlabel("epoch")
    ax.set_ylabel("validation loss (MSE of scaled PCA weights)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def marker_count_curve(rows: list[dict], path: Path) -> Path:
    """Test-1 mean Offset_max versus number of markers (study rows), with the paper's points."""
    plt = pyplot()
    n = np.array([r["n_markers"] for r in rows], dtype=float)
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for key, style, label in (("mlp_offset_max", "o-", "MLP"), ("rigid_offset_max", "^-", "rigid registration"),
                              ("ridge_offset_max", "s-", "ridge"), ("pca_floor_offset_max", "v--", "PCA floor")):
        if key in rows[0]:
            ax.semilogy(n, [r[key] for r in rows], style, ms=4, color=_STYLE[key.rsplit("_offset", 1)[0]][1],
                        label=f"{label} mean Offset_max")
    ax.semilogy(list(PAPER_MARKER_COUNTS), list(PAPER_MARKER_COUNTS.values()), "k*", ms=10, label="paper (MLP)")
    ax.set_xlabel("number of fiducial markers n_d")
    ax.set_ylabel("test-1 mean Offset_max (mm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def architecture_grid(rows: list[dict], path: Path) -> Path:
    """Mean test-1 Offset_max and training time over the hidden-layer grid."""
    plt = pyplot()
    n1 = sorted({r["n1"] for r in rows})
    n2 = sorted({r["n2"] for r in rows})
    err = np.full((len(n1), len(n2)), np.nan)
    sec = np.full((len(n1), len(n2)), np.nan)
    for i, a in enumerate(n1):
        for j, b in enumerate(n2):
            sel = [r for r in rows if r["n1"] == a and r["n2"] == b]
            if sel:
                err[i, j] = np.mean([r["mlp_offset_max"] for r in sel])
                sec[i, j] = np.mean([r["seconds"] for r in sel])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    panels = ((axes[0], err, "test-1 mean Offset_max (mm)", "{:.3f}"), (axes[1], sec, "training time (s)", "{:.1f}"))
    for ax, data, title, fmt in panels:
        im = ax.imshow(data, cmap="viridis")
        ax.set_xticks(range(len(n2)), n2)
        ax.set_yticks(range(len(n1)), n1)
        ax.set_xlabel("second hidden layer")
        ax.set_ylabel("first hidden layer")
        ax.set_title(title, fontsize=10)
        for i in range(len(n1)):
            for j in range(len(n2)):
                if np.isfinite(data[i, j]):
                    ax.text(j, i, fmt.format(data[i, j]), ha="center", va="center", color="w", fontsize=8)
        fig.colorbar(im, ax=ax)
    return save_figure(fig, path)
