"""Pictures of mixing: curves against revolutions and slices of the concentration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["mixing_curve", "snapshots", "save_report_figure"]


def _pyplot():
    import matplotlib

    if matplotlib.get_backend().lower() not in {"agg", "module://matplotlib_inline.backend_inline"}:
        try:
            matplotlib.use("Agg", force=False)
        except Exception:  # an interactive backend already in use is fine
            pass
    import matplotlib.pyplot as plt

    return plt


def mixing_curve(mixing, ax=None, floor=None, label=None):
    """RSD and segregation intensity against revolutions (log scale).

    Parameters
    ----------
    mixing : xarray.Dataset
        A mixing dataset.
    ax : matplotlib Axes, optional
    floor : float, optional
        Random-mixture intensity I_R to draw as a dashed line.
    label : str, optional
        Suffix for the legend entries.
    """
    plt = _pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4))
    rev = mixing["revolution"].values
    suffix = f" ({label})" if label else ""
    ax.semilogy(rev, mixing["rsd"].values, "-o", ms=3, label=f"RSD{suffix}")
    intensity = mixing["intensity"].values
    if np.isfinite(intensity).any():
        ax.semilogy(rev, intensity, "-s", ms=3, label=f"intensity{suffix}")
    if floor is not None:
        ax.axhline(floor, ls="--", color="k", lw=1, label="random mixture")
    ax.set_xlabel("revolutions")
    ax.set_ylabel("RSD, segregation intensity")
    ax.set_title(f"{mixing.attrs.get('scheme', '')}, k1 = {mixing.attrs.get('k1', float('nan')):g}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return ax


def snapshots(mixing, axis="z", position=0.0, max_panels=6):
    """Slices of c at the snapshot revolutions (2-D fields are shown whole)."""
    plt = _pyplot()
    c = mixing["c"]
    n = min(c.sizes["snapshot"], max_panels)
    fig, axes = plt.subplots(1, n, figsize=(2.6 * n, 2.8), squeeze=False)
    for i in range(n):
        field = c.isel(snapshot=i)
        if "z" in field.dims:
            field = field.sel({axis: position}, method="nearest")
        ax = axes[0, i]
        field.T.plot.imshow(
            ax=ax, vmin=0, vmax=1, cmap="coolwarm", add_colorbar=False, origin="lower"
        )
        ax.set_title(f"rev {float(c['snapshot_revolution'][i]):g}")
        ax.set_aspect("equal")
        ax.set_xlabel("")
        ax.set_ylabel("")
    fig.tight_layout()
    return fig


def save_report_figure(mixing, path, floor=None) -> Path:
    """Write a PNG with the mixing curve (left) and the last snapshot (right)."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    mixing_curve(mixing, ax=left, floor=floor)
    if mixing.sizes.get("snapshot", 0):
        field = mixing["c"].isel(snapshot=-1)
        if "z" in field.dims:
            field = field.sel(z=0.0, method="nearest")
        field.T.plot.imshow(
            ax=right,
            vmin=0,
            vmax=1,
            cmap="coolwarm",
            origin="lower",
            cbar_kwargs={"label": "c (species A)"},
        )
        right.set_aspect("equal")
        rev = float(mixing["snapshot_revolution"][-1])
        right.set_title(f"c after {rev:g} revolutions")
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path
