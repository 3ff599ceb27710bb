"""Studies of a scene: calibration of k1 (paper §5.2, Figs. 7–8).

The paper calibrates the spanwise diffusion constant k1 of eq. (5) on a rotating drum:
the 2-D model runs for several k1 values, each run stopped once the segregation
intensity reaches the random-mixture floor, and the k1 whose curve has the smallest sum
of absolute differences from the measured intensity over the measured revolutions is
taken (Fig. 8). :func:`calibrate_k1` does the same, refines the best value between the
grid points with a parabola, and returns every curve and cost as a labelled dataset;
:func:`calibration_figure` draws the paper's two figures from it.
"""

from __future__ import annotations

import csv
import math
import os
import time
import warnings
from pathlib import Path

import numpy as np
import xarray as xr

from ._version import __version__

__all__ = [
    "DEFAULT_K1",
    "METRICS",
    "CalibrationWarning",
    "calibrate_k1",
    "calibration_figure",
    "parabola_minimum",
    "read_curve",
]

#: The k1 values tried by default: the paper's Fig. 8 range around its k1 = 0.01.
DEFAULT_K1 = (0.0, 0.0025, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03)
#: The mixing curves a measurement may give, as named in a mixing dataset.
METRICS = ("intensity", "rsd")

_LONG_NAMES = {"intensity": "segregation intensity", "rsd": "relative standard deviation"}
_FLOOR_ATTRS = {"intensity": "random_mixture_intensity", "rsd": "random_mixture_rsd"}
_STOP_KEYS = {"intensity": "stop_intensity", "rsd": "stop_rsd"}
# Keywords calibrate_k1 sets itself for every run.
_OWN_KEYWORDS = {"revolutions", "stop_intensity", "stop_rsd"}
# Finest default spacing of the model's records, in revolutions.
_OUTPUT_EVERY = 0.25
# Revolutions closer than this count as the same (round-off of time / period).
_REV_TOL = 1e-9

COST_DEFINITION = (
    "sum over the measured revolutions r_i of |model(r_i) - measured(r_i)| (paper Fig. 8); "
    "model(r) is the run's curve clamped below at the random-mixture floor (when floor is "
    "on) and interpolated linearly in revolution on the log of the value"
)


class CalibrationWarning(UserWarning):
    """The calibration ran, but its answer needs care (best k1 at the grid's edge, ...)."""


# ----------------------------------------------------------------------------- input


def read_curve(curve, metric: str | None = None) -> xr.DataArray:
    """A measured mixing curve as a checked DataArray over ``revolution``.

    Parameters
    ----------
    curve : xarray.DataArray, str or path
        A DataArray over dim ``revolution`` (or over a dim carrying a ``revolution``
        coordinate, as a mixing dataset's ``intensity`` over ``time``), named
        ``"intensity"`` or ``"rsd"``; or a CSV file whose header row names its two
        columns: ``revolution`` (or ``revolutions``), then ``intensity`` or ``rsd``.
    metric : {"intensity", "rsd"}, optional
        What the values are; by default the DataArray's name or the CSV header says.

    Returns
    -------
    xarray.DataArray
        Named after the metric, over dim ``revolution`` sorted increasing, with CF
        attributes.

    Raises
    ------
    ValueError
        An unknown or conflicting metric, missing or unknown CSV columns, fewer than 2
        points, non-finite or negative values, negative or duplicate revolutions.
    """
    if metric is not None and metric not in METRICS:
        raise ValueError(f"metric {metric!r} is unknown; allowed: {', '.join(METRICS)}")
    if isinstance(curve, xr.DataArray):
        revolutions, values, named = _from_dataarray(curve)
    elif isinstance(curve, str | os.PathLike):
        revolutions, values, named = _from_csv(Path(curve))
    else:
        raise TypeError("measured must be a DataArray over revolution or a path to a CSV file")
    metric = _metric_of(named, metric)
    revolutions, values = _checked_points(revolutions, values, metric)
    return xr.DataArray(
        values,
        dims="revolution",
        coords={"revolution": ("revolution", revolutions, _revolution_attrs())},
        name=metric,
        attrs={"units": "1", "long_name": f"measured {_LONG_NAMES[metric]}"},
    )


def _from_dataarray(curve: xr.DataArray):
    if curve.ndim != 1:
        raise ValueError(f"measured: needs a 1-D curve over revolution, got dims {curve.dims}")
    if curve.dims[0] != "revolution":
        if "revolution" not in curve.coords or curve["revolution"].dims != curve.dims:
            raise ValueError(
                f"measured: the curve is over {curve.dims[0]!r} and has no revolution "
                "coordinate along it"
            )
        curve = curve.swap_dims({curve.dims[0]: "revolution"})
    revolutions = np.asarray(curve["revolution"].values, float)
    return revolutions, np.asarray(curve.values, float), curve.name


def _from_csv(path: Path):
    with path.open(newline="") as handle:
        rows = [row for row in csv.reader(handle) if any(cell.strip() for cell in row)]
    if not rows:
        raise ValueError(f"{path}: empty file; needs a header row 'revolution,intensity'")
    header = [cell.strip().lower() for cell in rows[0]]
    if len(header) != 2 or header[0] not in ("revolution", "revolutions"):
        raise ValueError(
            f"{path}: header {','.join(rows[0])!r} is not 'revolution,intensity' or "
            "'revolution,rsd'"
        )
    if header[1] not in METRICS:
        raise ValueError(
            f"{path}: column {rows[0][1].strip()!r} is unknown; the second column must be "
            f"one of {', '.join(METRICS)}"
        )
    table = []
    for number, row in enumerate(rows[1:], start=2):
        try:
            if len(row) != 2:
                raise ValueError
            table.append([float(cell) for cell in row])
        except ValueError:
            raise ValueError(f"{path}, row {number}: {row!r} is not two numbers") from None
    table = np.asarray(table, float).reshape(-1, 2)
    return table[:, 0], table[:, 1], header[1]


def _metric_of(named, metric: str | None) -> str:
    """The metric given, else the one the data is named after; a conflict is refused."""
    if metric is None:
        if named not in METRICS:
            raise ValueError(
                f"measured: cannot tell the metric from the name {named!r}; "
                f"pass metric= one of {', '.join(METRICS)}"
            )
        return named
    if named in METRICS and named != metric:
        raise ValueError(f"measured: the data is named {named!r} but metric={metric!r}")
    return metric


def _checked_points(revolutions: np.ndarray, values: np.ndarray, metric: str):
    if len(values) < 2:
        raise ValueError(f"measured: {len(values)} point(s); at least 2 are needed")
    if not (np.all(np.isfinite(revolutions)) and np.all(np.isfinite(values))):
        raise ValueError("measured: non-finite revolution or value (NaN or infinity)")
    if np.any(revolutions < 0):
        raise ValueError(f"measured: negative revolution {revolutions.min():g}; needs >= 0")
    if np.any(values < 0):
        raise ValueError(f"measured: negative {metric} {values.min():g}; needs >= 0")
    order = np.argsort(revolutions, kind="stable")
    revolutions, values = revolutions[order], values[order]
    repeated = revolutions[1:][np.diff(revolutions) <= _REV_TOL]
    if len(repeated):
        raise ValueError(f"measured: revolution {repeated[0]:g} appears more than once")
    return revolutions, values


def _revolution_attrs() -> dict:
    return {"units": "1", "long_name": "revolutions since the start of mixing"}


def _k1_grid(k1) -> np.ndarray:
    values = np.atleast_1d(np.asarray(DEFAULT_K1 if k1 is None else k1, float))
    if values.ndim != 1 or not np.all(np.isfinite(values)) or np.any(values < 0):
        raise ValueError(f"k1 grid {k1!r}: needs finite values >= 0")
    values = np.unique(values)
    if len(values) < 3:
        raise ValueError(f"k1 grid {k1!r}: needs at least 3 distinct values to bracket a minimum")
    return values


# ----------------------------------------------------------------------------- model curves


def _interp_log(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Interpolate fp(xp) at x linearly in xp on log(fp): exact for an exponential decay.

    A segment with a zero end (an unclamped curve reaching 0) is interpolated linearly.
    """
    j = np.clip(np.searchsorted(xp, x, side="right") - 1, 0, len(xp) - 2)
    w = np.clip((x - xp[j]) / (xp[j + 1] - xp[j]), 0.0, 1.0)
    a, b = fp[j], fp[j + 1]
    linear = a + w * (b - a)
    with np.errstate(divide="ignore", invalid="ignore"):
        geometric = a ** (1.0 - w) * b**w
    return np.where((a > 0) & (b > 0), geometric, linear)


def _model_curve(mixed: xr.Dataset, metric: str, revolutions: np.ndarray, floor: float | None):
    """The run's curve at the measured revolutions, clamped below at ``floor`` (if given).

    The records are clamped first and then interpolated, so a run stopped at the floor
    gives the same curve as one run on (its records past the stop would be clamped to the
    floor), and past its last record the curve is the floor.
    """
    rev = np.asarray(mixed["revolution"].values, float)
    values = np.asarray(mixed[metric].values, float)
    keep = np.isfinite(values)  # intensity is NaN where too few sampling cells qualify
    rev, values = rev[keep], values[keep]
    k1 = mixed.attrs.get("k1", math.nan)
    if len(rev) < 2 or rev[0] > revolutions[0] + _REV_TOL:
        raise ValueError(
            f"the run at k1 = {k1:g} has no finite {metric} from revolution "
            f"{revolutions[0]:g} on; check the sampling cell and min_intensity_cells"
        )
    if floor is not None:
        values = np.maximum(values, floor)
    out = _interp_log(revolutions, rev, values)
    beyond = revolutions > rev[-1] + _REV_TOL
    if beyond.any():
        stopped = str(mixed.attrs.get("stopped_by", ""))
        if floor is None or "floor" not in stopped:
            raise ValueError(
                f"the run at k1 = {k1:g} ended at revolution {rev[-1]:g} ({stopped}), "
                f"before the measured revolution {revolutions[-1]:g}"
            )
        out[beyond] = floor
    return out


def _floor_of(mixed: xr.Dataset, metric: str) -> float | None:
    value = float(mixed.attrs.get(_FLOOR_ATTRS[metric], math.nan))
    return value if math.isfinite(value) else None


def _output_every(revolutions: np.ndarray) -> float:
    """Records at least as fine as the measurements, and never coarser than a quarter turn."""
    return float(min(_OUTPUT_EVERY, np.diff(revolutions).min()))


class _Runner:
    """Runs the model for one k1 and returns its curve at the measured revolutions."""

    def __init__(self, flow, scene, measured: xr.DataArray, floor: bool, progress, overrides):
        self.flow, self.scene, self.progress = flow, scene, progress
        self.metric = measured.name
        self.revolutions = measured["revolution"].values
        self.use_floor = floor
        self.overrides = {"output_every": _output_every(self.revolutions), **overrides}
        # The floor stop saves the run time past the floor, where the clamped curve is
        # the floor anyway; without the clamp the whole curve is needed, so no stop at all
        # (a stop rule in the scene would cut it short).
        stops = {"stop_intensity": None, "stop_rsd": None}
        if floor:
            stops[_STOP_KEYS[self.metric]] = "floor"
        self.overrides.update(stops)
        self.floors: list[float | None] = []
        self.ends: list[float] = []

    def __call__(self, k1: float) -> np.ndarray:
        from .ade.stepper import mix

        mixed = mix(
            self.flow,
            self.scene,
            k1=float(k1),
            revolutions=float(self.revolutions[-1]),
            progress=self.progress,
            **self.overrides,
        )
        floor = _floor_of(mixed, self.metric) if self.use_floor else None
        self.floors.append(floor)
        self.ends.append(float(mixed["revolution"].values[-1]))
        return _model_curve(mixed, self.metric, self.revolutions, floor)


def _cost(model: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Sum of absolute differences over the measured revolutions (last axis), Fig. 8."""
    return np.abs(model - measured).sum(axis=-1)


# ----------------------------------------------------------------------------- refinement


def parabola_minimum(x, y) -> tuple[float, float, bool, bool]:
    """The minimum of sampled values, refined by a parabola through the lowest sample
    and its two neighbours.

    Parameters
    ----------
    x : array_like
        Strictly increasing sample positions (at least 3).
    y : array_like
        Values at ``x``.

    Returns
    -------
    x_min : float
        The parabola's vertex; the lowest sample itself when it is at an end of ``x`` or
        the three values are equal (no curvature).
    y_min : float
        The parabola's value at its vertex (the sample's value when not refined).
    refined : bool
        Whether ``x_min`` comes from the parabola.
    at_edge : bool
        Whether the lowest sample is the first or the last.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 3 or len(x) != len(y) or np.any(np.diff(x) <= 0):
        raise ValueError("parabola_minimum: needs >= 3 strictly increasing x and as many y")
    j = int(np.argmin(y))
    if j in (0, len(x) - 1):
        return float(x[j]), float(y[j]), False, True
    (x0, x1, x2), (y0, y1, y2) = x[j - 1 : j + 2], y[j - 1 : j + 2]
    # Vertex of the parabola through three unevenly spaced points (Lagrange form).
    num = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
    den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
    if not den < 0:  # den < 0 exactly when the parabola opens upwards
        return float(x1), float(y1), False, False
    vertex = x1 - 0.5 * num / den
    a = ((y2 - y1) / (x2 - x1) - (y1 - y0) / (x1 - x0)) / (x2 - x0)
    return float(vertex), float(y1 - a * (vertex - x1) ** 2), True, False


def _refine(grid, cost, runner, curves, measured, refine: bool) -> dict:
    """Best k1: the parabola's vertex, checked by a run when ``refine`` is on."""
    vertex, predicted, refined, at_edge = parabola_minimum(grid, cost)
    j = int(np.argmin(cost))
    out = {
        "grid_best_k1": float(grid[j]),
        "grid_best_cost": float(cost[j]),
        "best_k1": vertex,
        "best_cost": predicted,
        "best_cost_source": "grid" if not refined else "parabola (not run)",
        "refined": refined,
        "at_grid_edge": at_edge,
        "parabola_k1": vertex,
        "parabola_cost": predicted,
        "fitted": curves[j],
        "fitted_k1": float(grid[j]),
        "note": "",
    }
    if at_edge:
        end = "lower" if j == 0 else "upper"
        out["note"] = f"the minimum is at the {end} end of the k1 grid; widen the grid"
        warnings.warn(
            f"calibrate_k1: the lowest cost is at the {end} end of the k1 grid "
            f"(k1 = {grid[j]:g}); the best k1 may lie beyond it: widen the grid",
            CalibrationWarning,
            stacklevel=3,
        )
    if not (refined and refine):
        return out
    curve = runner(vertex)
    run_cost = float(_cost(curve, measured))
    out.update(refined_k1=vertex, refined_cost=run_cost)
    if run_cost <= cost[j]:
        out.update(best_cost=run_cost, best_cost_source="run", fitted=curve, fitted_k1=vertex)
    else:
        # the parabola misjudged an uneven cost: the run says the grid point is better
        out.update(best_k1=float(grid[j]), best_cost=float(cost[j]), best_cost_source="grid")
        out["note"] = (
            f"the run at the parabola's k1 = {vertex:.6g} costs {run_cost:.6g}, more than the "
            f"grid minimum {cost[j]:.6g}; the grid minimum is kept"
        )
    return out


# ----------------------------------------------------------------------------- study


def _resolve(scene, flow, cache):
    from .io import open_flow
    from .pipeline import scene_flow
    from .scene import load_scene

    scene = load_scene(scene)
    if flow is None:
        flow = scene_flow(scene, cache=cache)[0]
    elif isinstance(flow, str | os.PathLike):
        flow = open_flow(flow)
    elif not isinstance(flow, xr.Dataset):
        raise TypeError("flow must be a flow dataset, a path to a flow file or None")
    return scene, flow


def _check_overrides(scene, overrides: dict) -> None:
    clash = sorted(_OWN_KEYWORDS & set(overrides))
    if clash:
        raise TypeError(
            f"calibrate_k1 sets {', '.join(clash)} itself: the runs go to the last measured "
            "revolution and stop at the random-mixture floor when floor=True"
        )
    if scene["mixing"].get("k2") is not None and "k2" not in overrides:
        warnings.warn(
            f"calibrate_k1: the scene fixes mixing.k2 = {scene['mixing']['k2']:g}, so k2 stays "
            "fixed while k1 varies (without it k2 = 1.9 k1)",
            CalibrationWarning,
            stacklevel=3,
        )


def calibrate_k1(
    measured,
    scene,
    flow=None,
    k1=None,
    *,
    metric: str | None = None,
    floor: bool = True,
    refine: bool = True,
    cache=None,
    progress: bool | None = False,
    **mix_overrides,
) -> xr.Dataset:
    """Calibrate the spanwise diffusion constant k1 against a measured mixing curve.

    For every k1 of the grid the model runs through the scene's flow up to the last
    measured revolution; its curve, clamped below at the random-mixture floor, is taken
    at the measured revolutions, and the cost is the sum of the absolute differences
    from the measurement (the paper's §5.2 and Fig. 8). The best k1 is the vertex of
    the parabola through the grid's lowest cost and its two neighbours; with ``refine``
    the model runs once more there, and that k1 is kept only if its cost is no worse
    than the grid's lowest.

    Parameters
    ----------
    measured : xarray.DataArray, str or path
        The measured curve, read by :func:`read_curve`: a DataArray over ``revolution``
        named ``"intensity"`` or ``"rsd"``, or a CSV file with header
        ``revolution,intensity`` or ``revolution,rsd``.
    scene : Scene, str or mapping
        The scene of the experiment (vessel, loading, sampling cell, numerics).
    flow : xarray.Dataset or path, optional
        The flow to mix in; by default the scene's own
        (:func:`blendxr.pipeline.scene_flow`), made once and reused for every k1.
    k1 : sequence of float, optional
        The k1 values to try (>= 0, at least 3 distinct; sorted here); default
        :data:`DEFAULT_K1`.
    metric : {"intensity", "rsd"}, optional
        What ``measured`` holds, if its name or CSV header does not say.
    floor : bool
        Clamp the model's curve below at the random-mixture floor of the metric (the
        mixing result's ``random_mixture_intensity`` or ``random_mixture_rsd``), as a
        measurement cannot fall below it, and stop each run once it reaches the floor,
        as the paper does (past the stop the clamped curve is the floor). Off: the runs
        go to the last measured revolution and their curves are compared as they are.
    refine : bool
        Run the model at the parabola's k1 and report its cost.
    cache : path, optional
        Folder of cached flows, for a solver scene's flow.
    progress : bool or None
        Progress bar of each run (None: when the terminal is interactive).
    **mix_overrides
        More keywords for :func:`blendxr.mix` (``cells``, ``scheme``, ``output_every``,
        ...); ``output_every`` defaults to the finest spacing of the measured revolutions,
        at most 0.25.

    Returns
    -------
    xarray.Dataset
        Coordinates ``k1`` (the grid) and ``revolution`` (the measured ones); variables
        ``cost`` (k1), ``measured`` (revolution), ``fitted`` (revolution, the model at
        ``fitted_k1``, clamped as used), ``model`` (k1, revolution, every run's curve)
        and ``run_revolutions`` (k1, where each run ended). Attributes: ``best_k1``,
        ``best_cost``, ``best_cost_source`` ("run", "parabola (not run)" or "grid"),
        ``grid_best_k1``, ``grid_best_cost``, ``parabola_k1``, ``fitted_k1``,
        ``refined`` and ``at_grid_edge`` (0 or 1), ``metric``, ``scene``, ``floor``
        (NaN when off or undefined), ``cost_definition``, ``note``, ``wall_time_s``.

    Raises
    ------
    ValueError
        A bad measurement or k1 grid (see :func:`read_curve`), or a run whose curve does
        not cover the measured revolutions.
    TypeError
        A keyword that calibrate_k1 sets itself (revolutions, stop_intensity, stop_rsd).

    Warns
    -----
    CalibrationWarning
        The lowest cost is at an end of the grid, the scene fixes k2, or the floor is
        undefined (no clamp).

    Examples
    --------
    >>> result = calibrate_k1("drum.csv", "drum-2d")  # doctest: +SKIP
    >>> result.attrs["best_k1"]  # doctest: +SKIP
    """
    started = time.perf_counter()
    curve = read_curve(measured, metric)
    metric = str(curve.name)
    grid = _k1_grid(k1)
    scene, flow = _resolve(scene, flow, cache)
    _check_overrides(scene, mix_overrides)
    runner = _Runner(flow, scene, curve, floor, progress, mix_overrides)
    values = curve.values
    curves = np.stack([runner(value) for value in grid])
    cost = _cost(curves, values)
    best = _refine(grid, cost, runner, curves, values, refine)
    floor_value = _floor_used(runner.floors, floor, metric)
    attrs = _result_attrs(best, metric, scene, floor_value, refine)
    attrs["wall_time_s"] = time.perf_counter() - started
    return _result(curve, grid, cost, curves, runner.ends[: len(grid)], best, attrs)


def _floor_used(floors: list, floor: bool, metric: str) -> float:
    if not floor:
        return math.nan
    defined = [f for f in floors if f is not None]
    if not defined:
        warnings.warn(
            f"calibrate_k1: the random-mixture floor of the {metric} is undefined for this "
            "scene (sampling cell missing or below the particle size): curves not clamped",
            CalibrationWarning,
            stacklevel=3,
        )
        return math.nan
    return float(defined[0])


def _result_attrs(best: dict, metric: str, scene, floor_value: float, refine: bool) -> dict:
    attrs = {
        key: best[key]
        for key in (
            "best_k1",
            "best_cost",
            "best_cost_source",
            "grid_best_k1",
            "grid_best_cost",
            "parabola_k1",
            "fitted_k1",
        )
    }
    attrs.update(
        refined=int(best["refined"]),
        at_grid_edge=int(best["at_grid_edge"]),
        refine_run=int(refine and "refined_cost" in best),
        metric=metric,
        scene=scene.name,
        floor=floor_value,
        cost_definition=COST_DEFINITION,
        interpolation="linear in revolution on log(value) between the run's records",
        note=best["note"],
        blendxr_version=__version__,
    )
    if "refined_cost" in best:
        attrs["refined_cost"] = best["refined_cost"]
    return attrs


def _result(curve, grid, cost, curves, ends, best, attrs) -> xr.Dataset:
    metric = str(curve.name)
    what = _LONG_NAMES[metric]
    revolution = curve["revolution"]
    return xr.Dataset(
        {
            "cost": ("k1", cost, {"units": "1", "long_name": f"sum of |model - measured| {what}"}),
            "measured": (
                "revolution",
                curve.values,
                {"units": "1", "long_name": f"measured {what}"},
            ),
            "fitted": (
                "revolution",
                best["fitted"],
                {"units": "1", "long_name": f"model {what} at the best k1"},
            ),
            "model": (("k1", "revolution"), curves, {"units": "1", "long_name": f"model {what}"}),
            "run_revolutions": (
                "k1",
                np.asarray(ends, float),
                {"units": "1", "long_name": "revolutions run (a run stops at the floor)"},
            ),
        },
        coords={
            "k1": ("k1", grid, {"units": "1", "long_name": "spanwise diffusion constant k1"}),
            "revolution": ("revolution", revolution.values, _revolution_attrs()),
        },
        attrs={"title": f"blendxr k1 calibration ({metric})", **attrs},
    )


# ----------------------------------------------------------------------------- figure


def calibration_figure(result: xr.Dataset, max_curves: int = 5):
    """The calibration as the paper's Figs. 8 and 7: cost against k1, curves against
    revolutions.

    Parameters
    ----------
    result : xarray.Dataset
        What :func:`calibrate_k1` returns.
    max_curves : int
        How many of the grid's model curves to draw faintly behind the fitted one.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from .plot import _pyplot

    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    _cost_panel(left, result)
    _curve_panel(right, result, max_curves)
    fig.tight_layout()
    return fig


def _cost_panel(ax, result: xr.Dataset) -> None:
    a = result.attrs
    ax.plot(result["k1"].values, result["cost"].values, "-o", ms=4, label="grid")
    ax.plot(
        [a["best_k1"]],
        [a["best_cost"]],
        "*",
        ms=12,
        color="tab:red",
        label=f"best k1 = {a['best_k1']:.4g} ({a['best_cost_source']})",
    )
    ax.set_xlabel("k1")
    ax.set_ylabel(f"sum of |model - measured| {a['metric']}")
    ax.set_title(f"{a['scene']}: cost against k1 (Fig. 8)", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def _curve_panel(ax, result: xr.Dataset, max_curves: int) -> None:
    a = result.attrs
    rev = result["revolution"].values
    grid = result["k1"].values
    picks = np.unique(np.round(np.linspace(0, len(grid) - 1, min(max_curves, len(grid)))))
    for i in picks.astype(int):
        ax.plot(rev, result["model"].values[i], "-", lw=1, alpha=0.35, label=f"k1 = {grid[i]:g}")
    ax.plot(rev, result["measured"].values, "ko", ms=4, label="measured")
    ax.plot(rev, result["fitted"].values, "-", color="tab:red", lw=2, label="fitted")
    if math.isfinite(a.get("floor", math.nan)):
        ax.axhline(a["floor"], ls="--", color="k", lw=1, label="random mixture")
    ax.set_yscale("log")
    ax.set_xlabel("revolutions")
    ax.set_ylabel(_LONG_NAMES[a["metric"]])
    ax.set_title(f"measured and model curves, k1 = {a['fitted_k1']:.4g} (Fig. 7)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
