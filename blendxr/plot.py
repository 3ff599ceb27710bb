"""Pictures of mixing: curves against revolutions and slices of the concentration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = [
    "mixing_curve",
    "mixing_panels",
    "mid_planes",
    "snapshots",
    "save_mixing_figure",
    "save_snapshot_figure",
    "save_figure",
]


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


def save_figure(fig, path, dpi=110) -> Path:
    """Write a figure atomically (a unique temporary file, then rename) and close it."""
    from .io import _atomic_path

    plt = _pyplot()
    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    try:
        with _atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=fmt)
    finally:
        plt.close(fig)
    return path


def _floor_attr(mixing, name):
    value = float(mixing.attrs.get(name, np.nan))
    return value if np.isfinite(value) else None


def mixing_panels(mixing, axes=None, label=None):
    """RSD (left) and segregation intensity (right) against revolutions, log scale.

    The RSD panel shows the random-mixture RSD of the sampling cells and the 5 % line
    (the usual blend-uniformity acceptance); the intensity panel shows I only where at
    least ``min_intensity_cells`` sampling cells qualify, with the random-mixture floor
    I_R = 1/N, and says how many cells qualified.

    Parameters
    ----------
    mixing : xarray.Dataset
        A mixing dataset.
    axes : pair of matplotlib Axes, optional
    label : str, optional
        Legend label of the curves.

    Returns
    -------
    (Axes, Axes)
    """
    plt = _pyplot()
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(10, 4))
    left, right = axes
    rev = mixing["revolution"].values
    left.semilogy(rev, mixing["rsd"].values, "-", lw=1.5, label=label or "RSD")
    floor_rsd = _floor_attr(mixing, "random_mixture_rsd")
    if floor_rsd is not None:
        left.axhline(floor_rsd, ls="--", color="k", lw=1, label="random mixture")
    left.axhline(0.05, ls=":", color="tab:red", lw=1, label="RSD 5 %")
    left.set_xlabel("revolutions")
    left.set_ylabel("RSD (all cells)")
    left.grid(True, which="both", alpha=0.3)
    left.legend(fontsize=8)
    intensity = mixing["intensity"].values
    cells = mixing["intensity_cells"].values if "intensity_cells" in mixing else None
    least = int(mixing.attrs.get("min_intensity_cells", 2))
    cell_mm = 1e3 * float(mixing.attrs.get("sampling_cell", np.nan))
    if np.isfinite(intensity).any():
        right.semilogy(rev, intensity, "-", lw=1.5, color="tab:orange", label=label or "I")
        floor_i = _floor_attr(mixing, "random_mixture_intensity")
        if floor_i is not None:
            right.axhline(floor_i, ls="--", color="k", lw=1, label="random mixture 1/N")
        right.legend(fontsize=8)
    else:
        right.text(
            0.5,
            0.5,
            f"fewer than {least} sampling cells\nof {cell_mm:.3g} mm qualify",
            ha="center",
            va="center",
            transform=right.transAxes,
        )
    if cells is not None and len(cells):
        shown = cells[np.isfinite(intensity)]
        span = f"{shown.min()}-{shown.max()}" if len(shown) else "none"
        right.set_title(f"{cell_mm:.3g} mm cells, {span} qualify (>= {least} drawn)", fontsize=9)
    right.set_xlabel("revolutions")
    right.set_ylabel("segregation intensity")
    right.grid(True, which="both", alpha=0.3)
    a = mixing.attrs
    left.set_title(f"{a.get('scheme', '')}, k1 = {float(a.get('k1', np.nan)):g}", fontsize=9)
    return left, right


def save_mixing_figure(mixing, path) -> Path:
    """Write :func:`mixing_panels` as a PNG (atomically)."""
    left, _ = mixing_panels(mixing)
    fig = left.figure
    fig.tight_layout()
    return save_figure(fig, path)


def mid_planes(mixing, revolutions=None, max_columns=6):
    """Concentration on the mid-planes at chosen snapshot revolutions (the paper's Fig. 11).

    3-D: the plane z = 0 (across the rotation axis) above the plane x = 0 (along it);
    2-D: the whole field.

    Parameters
    ----------
    mixing : xarray.Dataset
    revolutions : sequence of float, optional
        Snapshot revolutions to show (the nearest stored ones); default: up to
        ``max_columns`` spread over the stored snapshots.
    max_columns : int

    Returns
    -------
    matplotlib Figure
    """
    plt = _pyplot()
    c = mixing["c"]
    stored = mixing["snapshot_revolution"].values
    if len(stored) == 0:
        raise ValueError("the mixing dataset holds no concentration snapshots")
    if revolutions is None:
        picks = np.unique(np.round(np.linspace(0, len(stored) - 1, min(max_columns, len(stored)))))
        index = [int(i) for i in picks]
    else:
        index = [int(np.argmin(np.abs(stored - r))) for r in revolutions]
    planes = [("z", "x")] if "z" not in c.dims else [("z", "x"), ("x", "z")]
    fig, axes = plt.subplots(
        len(planes), len(index), figsize=(2.4 * len(index) + 1, 2.5 * len(planes)), squeeze=False
    )
    image = None
    for row, (cut, across) in enumerate(planes):
        for col, i in enumerate(index):
            field = c.isel(snapshot=i)
            if cut in field.dims:
                field = field.sel({cut: 0.0}, method="nearest")
            ax = axes[row, col]
            image = ax.imshow(
                field.transpose("y", across).values,
                origin="lower",
                vmin=0,
                vmax=1,
                cmap="coolwarm",
                extent=_extent(field, across),
            )
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"rev {stored[i]:g}", fontsize=9)
            if col == 0:
                ax.set_ylabel(f"{cut} = 0" if cut in c.dims else "")
    fig.colorbar(image, ax=axes, shrink=0.8, label="c (species A)")
    return fig


def _extent(field, across):
    h = [float(field[d][1] - field[d][0]) for d in (across, "y")]
    xs, ys = field[across].values, field["y"].values
    return (xs[0] - h[0] / 2, xs[-1] + h[0] / 2, ys[0] - h[1] / 2, ys[-1] + h[1] / 2)


def save_snapshot_figure(mixing, path, revolutions=None) -> Path | None:
    """Write :func:`mid_planes` as a PNG (atomically); None when there are no snapshots."""
    if mixing.sizes.get("snapshot", 0) == 0:
        return None
    return save_figure(mid_planes(mixing, revolutions), path)
