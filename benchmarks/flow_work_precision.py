"""Work against precision of the built-in flow solver: wall time against velocity error.

Scene: the 2-D rolling drum of ``flow_drum.py`` (150 mm drum, half full, 10 rpm, Table 1
material with cohesion 0, E scaled down by 100 with ``solver.stiffness_scaling``,
settled 0.3 s, 2 revolutions; the flow is the lab-frame single-phase average of the
last revolution). The MPM background-grid cell ``solver.cell`` takes the values 5, 3.5
and 2.5 mm, and a reference run uses 1.75 mm; the OUTPUT grid (``flow.cell``, 5 mm)
is the same for every run, so each run's averaged velocity field lands on the same
cells as the reference's and the two are differenced cell by cell.

Errors against the reference, over the output cells with fill > 0.5 in both runs
(``|.|`` the length of the velocity vector in a cell):

- relative L1, ``Σ |v - v_ref| / Σ |v_ref|``, and relative L2,
  ``sqrt(Σ |v - v_ref|² / Σ |v_ref|²)``;
- max error, ``max |v - v_ref| / max |v_ref|`` (the worst cell against the largest
  reference speed);
- relative error of the largest downslope surface speed and the error (degrees) of the
  dynamic angle, both from ``blendxr.flow.diagnostics`` (``surface_velocity`` and
  ``surface_line``, as ``flow_drum.py`` uses them);
- observed orders between successive cells, ``log(e1 / e2) / log(h1 / h2)``. The
  reference is itself a finite run, so the error of the finest run is underestimated
  and its order overstated; and a one-revolution average of a granular flow carries
  noise of its own (the reference's periodicity attributes, revolution 1 against 2,
  give an idea of it), below which no error can fall.

Cost per run: wall time of the ``solve_flow`` call (set-up, stepping and the dataset;
the kernels are compiled or loaded from numba's cache on a tiny run first), steps,
particles and particle updates per second (the flow's ``particle_updates_per_s``
attribute, over the stepping loop). These 2-D beds are below the solver's parallel
threshold and run on one thread whatever ``NUMBA_NUM_THREADS`` says.

Run: ``python benchmarks/flow_work_precision.py`` (about 7 minutes on an idle machine by
the estimate a ``--quick`` run makes from its cost per particle update, 9 by
``flow_drum.py``'s timings of the 5 to 2.5 mm runs on a slower one; two thirds of it
the 1.75 mm reference: particles grow as 1/cell², steps as 1/cell, a run's cost as
1/cell³).
``--cells 5,3.5,2.5 --reference 1.75 --flow-cell 5`` (mm) change the cells.
``--quick`` checks the script in about 20 seconds: cells 10, 8 and 6 mm against a 5 mm
reference on a 15 mm output grid, at 30 rpm (shorter revolutions), and estimates the
full run's time from its own timings. ``--report`` rewrites the Markdown and the plot
from the JSON without running anything.

``--mu-i LIMIT_DEG DIAMETER_MM`` runs the same with the optional mu(I) friction
(``material.friction_angle_limit_deg``, ``material.particle_diameter``; docs/flow.md).

Writes ``benchmarks/results/flow_work_precision.{json,md,png}`` (with ``--quick``:
``flow_work_precision_quick.{json,md,png}``, so the real results stay; with ``--mu-i``:
``flow_work_precision_mu_i.*``).
"""

from __future__ import annotations

import os

# 2 threads as in every benchmark here, unless the caller sets the variable. The solver
# runs beds below its parallel threshold (all the 2-D beds here) on one thread anyway; a
# caller may pin the rest to one on a shared machine, where a 2-thread loop stalls
# whenever another process takes a core
os.environ.setdefault("NUMBA_NUM_THREADS", "2")

import argparse  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import flow_drum  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    RESULTS,
    Contention,
    cpu_pressure,
    echo,
    load_average,
    machine,
    machine_line,
    table,
    wait_for_quiet,
    write_atomic,
    write_json,
)

from blendxr.flow.diagnostics import surface_line, surface_velocity  # noqa: E402
from blendxr.flow.solver import solve_flow  # noqa: E402

NAME = "flow_work_precision"
# the drum, its fill and E scaling are flow_drum.py's (its cohesionless case)
DIAMETER = flow_drum.DIAMETER
FILL = flow_drum.FILL
COHESION = 0.0
STIFFNESS_SCALING = flow_drum.STIFFNESS_SCALING
FILL_MASK = 0.5  # output cells compared: fill above this in the run and in the reference

# the scene of flow_drum.py (cohesionless), solver cells in m
FULL = {
    "cells_m": [0.005, 0.0035, 0.0025],
    "reference_m": 0.00175,
    "flow_cell_m": 0.005,
    "rpm": 10.0,
    "settle_time_s": 0.3,
    "revolutions": 2,
}
# a check of the script: coarse cells and shorter revolutions (solver.revolutions is an
# integer of at least 2, so the revolutions are made shorter by turning faster)
QUICK = {
    "cells_m": [0.010, 0.008, 0.006],
    "reference_m": 0.005,
    "flow_cell_m": 0.015,
    "rpm": 30.0,
    "settle_time_s": 0.3,
    "revolutions": 2,
}
# the kernels' warm-up: a whole (tiny, fast-turning) run, so that every kernel a run
# calls, the deposit into the output grid included, is compiled before any timing
WARM_UP = {"cell_m": 0.02, "rpm": 30.0, "settle_time_s": 0.3}

MEASURES = ("l1", "l2", "max", "surface_speed", "angle")


def scene(cell: float, settings: dict, name: str | None = None) -> dict:
    """The drum of flow_drum.py with MPM cell ``cell`` on the common output grid."""
    out = flow_drum.scene(settings["flow_cell_m"], COHESION)
    out["name"] = name or f"drum-2d-work-precision-{cell * 1000:g}mm"
    out["operation"] = {"rpm": settings["rpm"]}
    out["material"].update(_mu_i_material(settings))
    out["solver"].update(
        cell=cell, settle_time=settings["settle_time_s"], revolutions=settings["revolutions"]
    )
    return out


def _mu_i_material(settings: dict) -> dict:
    """The material keys of the optional mu(I) friction (``--mu-i``)."""
    if settings.get("mu_i") is None:
        return {}
    limit, diameter = settings["mu_i"]
    return {"friction_angle_limit_deg": limit, "particle_diameter": diameter}


def simulated_time(settings: dict) -> float:
    return settings["settle_time_s"] + settings["revolutions"] * 60.0 / settings["rpm"]


def warm_up() -> float:
    """Compile (or load from numba's cache) every kernel of a run; returns the seconds."""
    settings = {
        "rpm": WARM_UP["rpm"],
        "flow_cell_m": WARM_UP["cell_m"],
        "settle_time_s": WARM_UP["settle_time_s"],
        "revolutions": 2,
    }
    started = time.perf_counter()
    solve_flow(scene(WARM_UP["cell_m"], settings, name="drum-2d-warm-up"), progress=False)
    return time.perf_counter() - started


def fields(flow) -> tuple[np.ndarray, np.ndarray]:
    """(fill (nx, ny), velocity (nx, ny, 2)) of the flow's single phase."""
    pick = {"rev_phase": 0} if "rev_phase" in flow.dims else {}
    fill = np.asarray(flow["fill"].isel(pick).transpose("x", "y").values, float)
    vel = np.stack(
        [np.asarray(flow[c].isel(pick).transpose("x", "y").values, float) for c in ("vx", "vy")],
        axis=-1,
    )
    return fill, vel


def surface(flow) -> dict:
    """Dynamic angle and largest downslope surface speed (None where no surface is found)."""
    try:
        line = surface_line(flow)
        sv = surface_velocity(flow, surface=line)
    except ValueError as err:
        return {"angle_deg": None, "max_surface_speed_m_s": None, "surface_error": str(err)}
    return {
        "angle_deg": float(line.angle_deg),
        "max_surface_speed_m_s": float(sv["max_speed"]),
        "s_at_max_m": float(sv["s_at_max"]),
        "surface_rms_residual_m": float(line.rms_residual),
        "chord_offset_m": float(line.offset),
    }


SOLVER_ATTRS = (
    "solver_cell_m",
    "particles",
    "steps",
    "simulated_time_s",
    "wall_time_s",
    "particle_updates_per_s",
    "dt_last_s",
    "periodicity_vx_norm",
    "periodicity_vy_norm",
)


def run_case(cell: float, settings: dict) -> tuple[dict, dict]:
    """One run: its cost and surface figures, and its fields (kept out of the JSON)."""
    with Contention() as meter:
        started = time.perf_counter()
        flow = solve_flow(scene(cell, settings), progress=False)
        wall = time.perf_counter() - started
    fill, vel = fields(flow)
    row = {
        "cell_m": cell,
        "wall_s": wall,
        "contention": meter.as_dict(),
        "solver": {k: flow.attrs.get(k) for k in SOLVER_ATTRS},
    }
    row["particles"] = int(row["solver"]["particles"])
    row["steps"] = int(row["solver"]["steps"])
    row.update(surface(flow))
    grid = {"x": np.asarray(flow["x"].values), "y": np.asarray(flow["y"].values)}
    return row, {"fill": fill, "vel": vel, **grid}


def errors(run: dict, ref: dict) -> dict:
    """Velocity errors of a run's fields against the reference's (see the module text)."""
    if not (np.allclose(run["x"], ref["x"]) and np.allclose(run["y"], ref["y"])):
        raise RuntimeError("the runs' output grids differ: the flow cell must be the same")
    full, full_ref = run["fill"] > FILL_MASK, ref["fill"] > FILL_MASK
    mask = full & full_ref
    diff = np.linalg.norm(run["vel"] - ref["vel"], axis=-1)
    speed_ref = np.linalg.norm(ref["vel"], axis=-1)
    d, s = diff[mask], speed_ref[mask]
    worst = np.unravel_index(int(np.argmax(np.where(mask, diff, -1.0))), diff.shape)
    return {
        "cells_compared": int(mask.sum()),
        "cells_full_in_one_only": int((full ^ full_ref).sum()),
        "fill_relative_l1": float(np.abs(run["fill"] - ref["fill"]).sum() / ref["fill"].sum()),
        "l1": float(d.sum() / s.sum()),
        "l2": float(np.sqrt((d**2).sum() / (s**2).sum())),
        "max": float(d.max() / s.max()),
        "max_abs_m_s": float(d.max()),
        "max_at_m": [float(ref["x"][worst[0]]), float(ref["y"][worst[1]])],
        "max_reference_speed_m_s": float(s.max()),
    }


def _difference(value, reference, relative: bool):
    if value is None or reference is None:
        return None
    return value / reference - 1.0 if relative else value - reference


def observed_orders(rows: list[dict], key: str) -> list[float | None]:
    """log(e1 / e2) / log(h1 / h2) between successive runs (None for the first)."""
    out: list[float | None] = [None]
    for a, b in zip(rows[:-1], rows[1:], strict=True):
        ea, eb = a["errors"].get(key), b["errors"].get(key)
        if ea is None or eb is None or ea == 0 or eb == 0:
            out.append(None)
            continue
        out.append(math.log(abs(ea) / abs(eb)) / math.log(a["cell_m"] / b["cell_m"]))
    return out


def estimate_full(rows: list[dict], reference: dict, quick: dict, full: dict) -> dict:
    """Wall time of the full run, from the quick runs' cost per particle update.

    Particles scale as 1/cell², steps as 1/cell times the ratio of the simulated times;
    the rate is that of the largest quick bed (the full beds are larger and, with less
    per-step overhead per particle, somewhat faster, so the estimate errs long).
    """
    base = max([*rows, reference], key=lambda r: r["particles"])
    rate = base["particles"] * base["steps"] / base["wall_s"]
    time_ratio = simulated_time(full) / simulated_time(quick)
    runs = []
    for cell in [*full["cells_m"], full["reference_m"]]:
        k = base["cell_m"] / cell
        particles = base["particles"] * k**2
        steps = base["steps"] * k * time_ratio
        runs.append(
            {
                "cell_m": cell,
                "particles": round(particles),
                "steps": round(steps),
                "wall_s": particles * steps / rate,
            }
        )
    return {
        "from_cell_m": base["cell_m"],
        "updates_per_s": rate,
        "simulated_time_ratio": time_ratio,
        "runs": runs,
        "total_s": sum(r["wall_s"] for r in runs),
    }


def measure(settings: dict, name: str, quick: bool) -> dict:
    quiet = wait_for_quiet()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    started = time.perf_counter()
    warm_s = warm_up()
    echo(f"warm-up {warm_s:.1f} s")
    rows, kept = [], []
    for cell in [*settings["cells_m"], settings["reference_m"]]:
        row, data = run_case(cell, settings)
        rows.append(row)
        kept.append(data)
        echo(
            f"solver cell {cell * 1000:g} mm: {row['particles']} particles, {row['steps']} "
            f"steps, wall {row['wall_s']:.1f} s, angle {_num(row['angle_deg'], '.2f')}°, "
            f"max surface speed {_num(row['max_surface_speed_m_s'], '.4f')} m/s"
        )
    reference, ref_data = rows.pop(), kept.pop()
    for row, data in zip(rows, kept, strict=True):
        row["errors"] = errors(data, ref_data)
        row["errors"]["surface_speed"] = _difference(
            row["max_surface_speed_m_s"], reference["max_surface_speed_m_s"], relative=True
        )
        row["errors"]["angle"] = _difference(
            row["angle_deg"], reference["angle_deg"], relative=False
        )
    for key in MEASURES:
        for row, order in zip(rows, observed_orders(rows, key), strict=True):
            row.setdefault("orders", {})[key] = order
    payload = {
        "benchmark": name,
        "quick": quick,
        "machine": info,
        "settings": {
            **settings,
            "diameter_m": DIAMETER,
            "fill_fraction": FILL,
            "cohesion_pa": COHESION,
            "stiffness_scaling": STIFFNESS_SCALING,
            "fill_mask": FILL_MASK,
            "warm_up_s": warm_s,
            "definitions": {
                "l1": "sum |v - v_ref| / sum |v_ref| over the output cells with fill > "
                f"{FILL_MASK} in both runs (|.|: length of the velocity vector)",
                "l2": "sqrt(sum |v - v_ref|^2 / sum |v_ref|^2) over the same cells",
                "max": "max |v - v_ref| / max |v_ref| over the same cells",
                "surface_speed": "largest downslope surface speed (surface_velocity) / the "
                "reference's - 1",
                "angle": "dynamic angle (surface_line) - the reference's, degrees",
                "order": "log(e1 / e2) / log(h1 / h2) between successive solver cells",
                "wall_s": "wall clock of one solve_flow call (set-up, stepping, dataset) "
                "after a warm-up run; single run, the machine may be shared",
                "particle_updates_per_s": "the flow's attribute: particle updates over "
                "the stepping loop's wall time",
            },
        },
        "runs": rows,
        "reference": reference,
        "total_s": time.perf_counter() - started,
        "load_average_at_end": load_average(),
        "cpu_pressure_at_end": cpu_pressure(),
    }
    if quick:
        payload["estimate_full"] = estimate_full(rows, reference, settings, FULL)
    path = write_json(name, payload)
    echo(f"wrote {path.relative_to(path.parents[2])}")
    return payload


# ----------------------------------------------------------------------------- report


def _pct(x, signed: bool = False) -> str:
    if x is None or x != x:
        return "n/a"
    return f"{100 * x:+.2f} %" if signed else f"{100 * x:.2f} %"


def _num(x, fmt: str) -> str:
    return "n/a" if x is None or x != x else format(x, fmt)


def _others(row) -> str:
    share = row["contention"]["other_cpu_share"]
    return "n/a" if share is None else f"{100 * share:.0f} %"


def _cost(row: dict) -> list:
    rate = row["solver"].get("particle_updates_per_s")
    return [
        f"{row['cell_m'] * 1000:g}",
        row["particles"],
        row["steps"],
        f"{row['wall_s']:.1f}",
        _num(None if rate is None else rate / 1e6, ".2f"),
    ]


def main_table(payload: dict) -> str:
    rows = []
    for r in payload["runs"]:
        e, o = r["errors"], r["orders"]
        rows.append(
            _cost(r)
            + [
                _pct(e["l1"]),
                _pct(e["l2"]),
                _pct(e["max"]),
                _pct(e["surface_speed"], signed=True),
                _num(e["angle"], "+.2f"),
                f"{_num(o['l1'], '.2f')} / {_num(o['l2'], '.2f')}",
                _others(r),
            ]
        )
    ref = payload["reference"]
    rows.append(_cost(ref) + ["(reference)", "", "", "", "", "", _others(ref)])
    return table(
        [
            "cell mm",
            "particles",
            "steps",
            "wall s",
            "M updates/s",
            "L1",
            "L2",
            "max err",
            "surface speed err",
            "angle err °",
            "order L1 / L2",
            "others' CPU",
        ],
        rows,
    )


def values_table(payload: dict) -> str:
    rows = []
    for r in [*payload["runs"], payload["reference"]]:
        e = r.get("errors")
        o = r.get("orders", {})
        rows.append(
            [
                f"{r['cell_m'] * 1000:g}",
                _num(r["angle_deg"], ".2f"),
                _num(r["max_surface_speed_m_s"], ".4f"),
                "" if e is None else e["cells_compared"],
                "" if e is None else e["cells_full_in_one_only"],
                "" if e is None else _pct(e["fill_relative_l1"]),
                "" if e is None else f"{e['max_abs_m_s']:.4f}",
                ""
                if e is None
                else f"({e['max_at_m'][0] * 1000:.0f}, {e['max_at_m'][1] * 1000:.0f})",
                "" if e is None else _num(o.get("max"), ".2f"),
                "" if e is None else _num(o.get("surface_speed"), ".2f"),
                f"{_pct(r['solver'].get('periodicity_vx_norm'))} / "
                f"{_pct(r['solver'].get('periodicity_vy_norm'))}",
            ]
        )
    return table(
        [
            "cell mm",
            "angle °",
            "max surface speed m/s",
            "cells compared",
            "cells full in one only",
            "fill L1 diff",
            "worst cell error m/s",
            "at (x, y) mm",
            "order max",
            "order surface speed",
            "rev 1 vs 2 (norm) vx / vy",
        ],
        rows,
    )


def estimate_table(estimate: dict) -> str:
    rows = [
        [f"{r['cell_m'] * 1000:g}", r["particles"], r["steps"], f"{r['wall_s']:.0f}"]
        for r in estimate["runs"]
    ]
    rows.append(["total", "", "", f"{estimate['total_s']:.0f}"])
    return table(["cell mm", "particles", "steps", "wall s"], rows)


def plot(payload: dict, path) -> None:
    """Errors against wall time and against the solver cell (log-log)."""
    runs = payload["runs"]
    series = (
        ("l1", "L1", "o-", "tab:blue"),
        ("l2", "L2", "s-", "tab:orange"),
        ("max", "max err", "^-", "tab:green"),
        ("surface_speed", "|surface speed err|", "d--", "tab:red"),
    )
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    for ax, xkey in zip(axes, ("wall_s", "cell_m"), strict=True):
        for key, label, style, colour in series:
            pts = [
                (r[xkey] * (1000 if xkey == "cell_m" else 1), abs(r["errors"][key]))
                for r in runs
                if r["errors"].get(key) not in (None, 0.0)
            ]
            if not pts:
                continue
            x, y = zip(*pts, strict=True)
            ax.loglog(x, y, style, color=colour, label=label)
        ax.grid(True, which="both", alpha=0.3)
    for r in runs:
        e = r["errors"]["l2"]
        if e:
            axes[0].annotate(
                f"{r['cell_m'] * 1000:g} mm",
                (r["wall_s"], e),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
            )
    # guides through the coarsest run's L2 error: first and second order
    first = runs[0]
    if first["errors"]["l2"]:
        h = np.array([r["cell_m"] * 1000 for r in runs])
        for p, style in ((1, "k:"), (2, "k-.")):
            axes[1].loglog(
                h, first["errors"]["l2"] * (h / h[0]) ** p, style, lw=0.8, label=f"order {p}"
            )
    ref_mm = payload["reference"]["cell_m"] * 1000
    flow_mm = payload["settings"]["flow_cell_m"] * 1000
    axes[0].set_xlabel("wall time of the solve_flow call (s)")
    axes[0].set_ylabel("relative error against the reference")
    axes[0].set_title(f"flow solver, 2-D drum: work-precision (reference {ref_mm:g} mm)")
    axes[1].set_xlabel("solver cell (mm)")
    axes[1].set_title(f"error against the solver cell (output cell {flow_mm:g} mm)")
    axes[1].legend(fontsize=8)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buffer.getvalue())


def _rheology_text(s: dict) -> str:
    if s.get("mu_i") is None:
        return (
            "Rheology: rate-independent Mohr-Coulomb (the paper's model), with lost contact "
            "bounded by the packing (`solver.lost_contact`, the default; docs/flow.md).\n\n"
        )
    limit, diameter = s["mu_i"]
    return (
        f"Rheology: **mu(I)** friction (`material.friction_angle_limit_deg = {limit:g}`, "
        f"grain diameter {diameter * 1000:g} mm, I0 = 0.279; docs/flow.md), with lost "
        "contact bounded by the packing (`solver.lost_contact`, the default).\n\n"
    )


def render(payload: dict, name: str) -> None:
    """Print the tables and write <name>.md and <name>.png from the results."""
    info, s = payload["machine"], payload["settings"]
    t_main, t_values = main_table(payload), values_table(payload)
    echo()
    echo(t_main)
    echo()
    echo(t_values)
    cells = " / ".join(f"{c * 1000:g}" for c in s["cells_m"])
    ref_mm = s["reference_m"] * 1000
    quick = ""
    estimate = payload.get("estimate_full")
    if payload.get("quick"):
        quick = (
            "**Quick check** (`--quick`): coarse cells and shorter revolutions, to test the "
            "script; the figures say nothing about the solver's accuracy at its working "
            "cells.\n\n"
        )
    est_text = ""
    if estimate is not None:
        t_est = estimate_table(estimate)
        echo()
        echo(f"estimated full run ({estimate['total_s'] / 60:.1f} min):")
        echo(t_est)
        est_text = f"""
## Estimated full run

From this run's cost per particle update at {estimate["from_cell_m"] * 1000:g} mm
({estimate["updates_per_s"] / 1e6:.2f} M/s, set-up included), with particles as
1/cell², steps as 1/cell and the simulated time {estimate["simulated_time_ratio"]:.2f} times
as long: about {estimate["total_s"] / 60:.0f} minutes, warm-up not counted (larger beds
update somewhat faster, so this errs long).

{t_est}
"""

    md = f"""<!-- written by benchmarks/flow_work_precision.py -->
# Work against precision of the flow solver (2-D rolling drum)

Machine: {machine_line(info)}. Whole script {payload["total_s"]:.0f} s (warm-up
{s["warm_up_s"]:.1f} s).

{quick}{_rheology_text(s)}Scene: the drum of `flow_drum.py`: {s["diameter_m"] * 1000:g} mm across,
`fill.fraction = {s["fill_fraction"]}`, {s["rpm"]:g} rpm, cohesion {s["cohesion_pa"]:g} Pa,
E / {s["stiffness_scaling"]:g} (`solver.stiffness_scaling`), settled {s["settle_time_s"]} s,
{s["revolutions"]} revolutions, lab-frame average of the last one. The MPM cell
`solver.cell` is {cells} mm, the reference {ref_mm:g} mm; every run writes its flow on the
same {s["flow_cell_m"] * 1000:g} mm output grid (`flow.cell`), where the fields are
differenced cell by cell.

Errors against the reference over the output cells with fill > {s["fill_mask"]} in both:
L1 = Σ |v - v_ref| / Σ |v_ref|, L2 = sqrt(Σ |v - v_ref|² / Σ |v_ref|²), max err =
max |v - v_ref| / max |v_ref| (|.| the length of the velocity vector); surface speed err:
the largest downslope surface speed (`surface_velocity`) over the reference's, - 1;
angle err: the dynamic angle (`surface_line`) less the reference's. Order:
log(e1 / e2) / log(h1 / h2) from successive cells. The reference is a finite run too:
the finest run's error is underestimated and its order overstated.

Cost: wall time of one `solve_flow` call after a warm-up run (set-up, stepping, dataset);
M updates/s: the flow's `particle_updates_per_s` (stepping loop only). These beds run on
one thread. The machine may be shared: "others' CPU" is the CPU time other processes
used during the run, as a share of the machine; the errors do not depend on the load.

![error against wall time]({name}.png)

{t_main}

Values behind the errors: "cells full in one only": output cells with fill > {s["fill_mask"]}
in the run or in the reference but not both (where the bed's outline differs); "fill L1
diff": Σ |fill - fill_ref| / Σ fill_ref over all cells; the worst cell's velocity
difference and its place; "rev 1 vs 2": the solver's `periodicity_*_norm` attributes,
Σ |Δv| / Σ |v| between the averages of revolutions 1 and 2 (the first includes the
start from rest): an upper bound on how much a one-revolution average moves by itself.

{t_values}
{est_text}"""
    write_atomic(RESULTS / f"{name}.md", md)
    plot(payload, RESULTS / f"{name}.png")
    echo()
    echo(f"wrote {name}.md, {name}.png")


def _mm_list(text: str) -> list[float]:
    try:
        values = [float(v) / 1000.0 for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of mm: {text!r}") from None
    if not values or min(values) <= 0:
        raise argparse.ArgumentTypeError(f"cells must be positive, got {text!r}")
    return values


def _mm(text: str) -> float:
    (value,) = _mm_list(text)
    return value


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cells",
        type=_mm_list,
        help="solver cells in mm, comma-separated (default 5,3.5,2.5; --quick: 10,8,6)",
    )
    parser.add_argument(
        "--reference", type=_mm, help="reference solver cell, mm (default 1.75; --quick: 5)"
    )
    parser.add_argument(
        "--flow-cell", type=_mm, help="common output cell, mm (default 5; --quick: 15)"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"a short check of the script; writes results/{NAME}_quick.*",
    )
    parser.add_argument(
        "--report",
        action="store_true",
        help=f"only rewrite {NAME}.md and {NAME}.png from results/{NAME}.json "
        "(with --quick: the _quick files)",
    )
    parser.add_argument(
        "--mu-i",
        nargs=2,
        type=float,
        metavar=("LIMIT_DEG", "DIAMETER_MM"),
        help="the optional mu(I) friction: limit angle (deg) and grain diameter (mm); "
        f"writes results/{NAME}_mu_i.*",
    )
    args = parser.parse_args(argv)
    name = NAME + ("_mu_i" if args.mu_i else "") + ("_quick" if args.quick else "")
    if args.report:
        payload = json.loads((RESULTS / f"{name}.json").read_text())
    else:
        settings = dict(QUICK if args.quick else FULL)
        if args.cells is not None:
            settings["cells_m"] = args.cells
        if args.reference is not None:
            settings["reference_m"] = args.reference
        if args.flow_cell is not None:
            settings["flow_cell_m"] = args.flow_cell
        settings["cells_m"] = sorted(settings["cells_m"], reverse=True)
        if args.mu_i:
            settings["mu_i"] = [args.mu_i[0], args.mu_i[1] / 1000.0]
        if settings["reference_m"] >= min(settings["cells_m"]):
            parser.error("the reference cell must be finer than every solver cell")
        payload = measure(settings, name, args.quick)
    render(payload, name)


if __name__ == "__main__":
    main()
