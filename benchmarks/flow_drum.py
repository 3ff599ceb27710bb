"""The built-in flow solver on the 2-D rolling drum: accuracy against the rolling-drum facts.

Scene: a 150 mm drum, half full (``fill.fraction = 0.5``), 10 rpm, the paper's Table 1
material with cohesion 0 (where the dynamic angle should be close to φ = 27.1°) and with
the paper's c = 87 Pa, E scaled down by 100 (``solver.stiffness_scaling``; its error is
measured by ``flow_stiffness.py``), settled for 0.3 s and turned for 2 revolutions; the
flow is the lab-frame average of the last revolution. Cell sizes 5, 3.5, 2.5 and 1.75 mm.

Per run, with ``blendxr.flow.diagnostics``:

- the free surface (fill = 0.5 crossings along normals to the surface, middle 80 % of
  the chord, total least squares line): dynamic angle, flatness (rms and largest
  distance of the crossings from the line), chord offset from the axis, half-chord L;
- the downslope flux through the flowing layer at s/L = -0.6 ... 0.6 against
  DESIGN §7's thin-layer flux ``ω (L² - s²)/2`` and against the rigid-bed balance
  ``ω (r_e² - r_b²)/2`` (r_e the bed's outer edge, r_b the base of the downslope
  motion, both measured on the same line); the upslope flux below the layer (mass
  balance); the layer depth and the gap between the bed's edge and the wall;
- the downslope speed along the surface: profile and maximum; its differences between
  successive cells (convergence);
- the solver's periodicity attributes (eq. 30 between revolutions 1 and 2), wall time
  and particle updates per second (``flow.attrs``).

A diagnostic experiment: the cohesionless 5 mm case again with the solver's wall band
(``blendxr.flow.solver.WALL_BAND``, nodes nearer to the wall than that many cells feel
the wall) set to 0 at run time, to show where the bed's stand-off from the wall comes from.
Another: the cohesionless case at 3.5 mm with E / 100 and no dilation, and with E / 10
with and without Table 1's dilation angle, to show what the stiffness scaling (elastic
compaction) and the dilation add to the layer's thin-layer deficit.

Run: ``python benchmarks/flow_drum.py`` (about 23 minutes; the 2-D beds run on one core). Writes
``benchmarks/results/flow_drum.{json,md,png}``; ``--report`` rewrites the Markdown and
the plot from the JSON without running anything.
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

import blendxr.flow.solver as solver  # noqa: E402
from blendxr.flow.diagnostics import (  # noqa: E402
    layer_flux,
    surface_line,
    surface_velocity,
)
from blendxr.flow.solver import FlowSimulation, solve_flow  # noqa: E402

DIAMETER = 0.15
RPM = 10.0
FILL = 0.5
COHESIONS = (0.0, 87.0)
CELLS = (0.005, 0.0035, 0.0025, 0.00175)
STIFFNESS_SCALING = 100.0
SETTLE_S = 0.3
REVOLUTIONS = 2
PHI_DEG = 27.1
S_FRACTIONS = (-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6)
MIDDLE = 0.4  # |s|/L within which the flux is summarised
# (stiffness scaling, dilation angle in degrees): the cohesionless drum at one cell with
# stiffer and non-dilating material, to tell the layer's own depth from what the E / 100
# scaling (elastic compaction) and Table 1's dilation angle (a bed that keeps dilating)
# add to the thin-layer deficit
MATERIAL_CELL = 0.0035
MATERIAL_CASES = ((100.0, 0.0), (10.0, 0.1), (10.0, 0.0))
#: the variant ``--projection N`` sets: its own results file, the cohesionless cell study
#: alone, every scene with these solver and material values
VARIANT = {"name": "flow_drum", "solver": {}, "material": {}, "note": ""}


def scene(
    cell: float,
    cohesion: float,
    stiffness_scaling: float = STIFFNESS_SCALING,
    dilation_angle_deg: float | None = None,
) -> dict:
    material = {"cohesion": cohesion, **VARIANT["material"]}
    if dilation_angle_deg is not None:
        material["dilation_angle_deg"] = dilation_angle_deg
    return {
        "name": f"drum-2d-c{cohesion:g}-{cell * 1000:g}mm",
        "vessel": {"kind": "drum", "ndim": 2, "diameter": DIAMETER},
        "operation": {"rpm": RPM},
        "fill": {"fraction": FILL},
        "material": material,
        "flow": {"cell": cell},
        "solver": {
            "stiffness_scaling": stiffness_scaling,
            "settle_time": SETTLE_S,
            "revolutions": REVOLUTIONS,
            "checkpoint_every": 1e9,
            **VARIANT["solver"],
        },
    }


def analyse(flow) -> dict:
    """Surface, flux and surface speed of one flow (see the module docstring)."""
    h = float(flow.attrs["solver_cell_m"])
    omega = 2.0 * math.pi * float(flow.attrs["rpm"]) / 60.0
    line = surface_line(flow)
    column = surface_line(flow, method="column")
    s = np.array(S_FRACTIONS) * line.half_chord
    q = layer_flux(flow, s, surface=line)
    sv = surface_velocity(flow, surface=line)
    flux = q["flux"].values
    thin = q["thin_layer_flux"].values
    rigid = q["rigid_flux_below"].values
    middle = np.abs(np.array(S_FRACTIONS)) <= MIDDLE + 1e-9
    return {
        "angle_deg": line.angle_deg,
        "angle_column_deg": column.angle_deg,
        "surface_rms_residual_m": line.rms_residual,
        "surface_max_residual_m": line.max_residual,
        "surface_rms_residual_cells": line.rms_residual / h,
        "surface_max_residual_cells": line.max_residual / h,
        "chord_offset_m": line.offset,
        "half_chord_m": line.half_chord,
        "omega_rad_s": omega,
        "flux": {
            "s_over_L": list(S_FRACTIONS),
            "s_m": s.tolist(),
            "flux_m2_s": flux.tolist(),
            "thin_layer_flux_m2_s": thin.tolist(),
            "rigid_bed_flux_m2_s": rigid.tolist(),
            "upslope_flux_m2_s": q["upslope_flux"].values.tolist(),
            "layer_depth_m": q["layer_depth"].values.tolist(),
            "wall_gap_m": q["wall_gap"].values.tolist(),
            "flux_over_thin_layer": (flux / thin).tolist(),
            "flux_over_rigid_bed": (flux / rigid).tolist(),
            "upslope_over_downslope": (q["upslope_flux"].values / flux).tolist(),
        },
        "middle": {
            "range_s_over_L": MIDDLE,
            "flux_error_thin_layer_max": float(np.max(np.abs(flux / thin - 1)[middle])),
            "flux_error_thin_layer_mean": float(np.mean((flux / thin - 1)[middle])),
            "flux_error_rigid_bed_max": float(np.max(np.abs(flux / rigid - 1)[middle])),
            "mass_balance_error_max": float(
                np.max(np.abs(q["upslope_flux"].values / flux - 1)[middle])
            ),
            "layer_depth_mid_m": float(q["layer_depth"].values[len(S_FRACTIONS) // 2]),
            "wall_gap_mean_m": float(np.mean(q["wall_gap"].values[middle])),
        },
        "surface_speed": {
            "s_m": sv["s"].values.tolist(),
            "speed_m_s": sv["speed"].values.tolist(),
            "max_m_s": float(sv["max_speed"]),
            "s_at_max_m": float(sv["s_at_max"]),
        },
    }


SOLVER_ATTRS = (
    "particles",
    "steps",
    "simulated_time_s",
    "wall_time_s",
    "particle_updates_per_s",
    "dt_last_s",
    "p_wave_speed_m_s",
    "material_volume_m3",
    "fill_volume_before_clipping_m3",
    "fill_clipped_max",
    "fill_volume_m3",
    "occupied_volume_over_seeded",
    "periodicity_vx",
    "periodicity_vy",
    "periodicity_vx_norm",
    "periodicity_vy_norm",
)


def run_case(cell: float, cohesion: float, label: str | None = None, **material) -> dict:
    """One drum run; ``material`` goes to :func:`scene` (stiffness scaling, dilation)."""
    with Contention() as meter:
        started = time.perf_counter()
        flow, particles = solve_flow(
            scene(cell, cohesion, **material), particles=True, progress=False
        )
        wall = time.perf_counter() - started
    row = {
        "case": label or f"c = {cohesion:g} Pa",
        "cohesion_pa": cohesion,
        "cell_m": cell,
        "wall_s": wall,
        "contention": meter.as_dict(),
        "solver": {k: flow.attrs.get(k) for k in SOLVER_ATTRS},
    }
    row.update(analyse(flow))
    fill = flow["fill"].values
    row["fill_volume_m3"] = float(fill.sum()) * cell**2
    # the particles' current volumes (J times the seeded ones) at the end of the run
    row["particle_volume_growth"] = float(
        particles["volume"].sum() / particles["volume0"].sum() - 1.0
    )
    return row


def wall_band_experiment(cell: float) -> dict | None:
    """The cohesionless case with the wall band set to 0 at run time (no file changed)."""
    if not hasattr(solver, "WALL_BAND"):
        return None
    default = solver.WALL_BAND
    try:
        solver.WALL_BAND = 0.0
        row = run_case(cell, 0.0, label="c = 0 Pa, wall band 0")
    finally:
        solver.WALL_BAND = default
    row["wall_band_cells"] = 0.0
    row["default_wall_band_cells"] = default
    row["experiment"] = "wall band"
    return row


def material_experiments() -> list[dict]:
    """The cohesionless drum at MATERIAL_CELL with other stiffness scalings and dilation."""
    rows = []
    for scaling, psi in MATERIAL_CASES:
        label = f"c = 0 Pa, E / {scaling:g}, psi = {psi:g}"
        row = run_case(
            MATERIAL_CELL, 0.0, label=label, stiffness_scaling=scaling, dilation_angle_deg=psi
        )
        row.update(experiment="material", stiffness_scaling=scaling, dilation_angle_deg=psi)
        rows.append(row)
        echo(
            f"{label}, {MATERIAL_CELL * 1000:g} mm: flux/thin (s=0) "
            f"{row['flux']['flux_over_thin_layer'][3]:.3f}, wall {row['wall_s']:.0f} s"
        )
    return rows


def is_experiment(row: dict) -> bool:
    """Rows that change the solver or the material, left out of the cell study."""
    return "experiment" in row or "wall_band_cells" in row


def convergence(rows: list[dict]) -> list[dict]:
    """Differences of key figures between successive cells, per cohesion."""
    out = []
    for cohesion in COHESIONS:
        runs = sorted(
            (r for r in rows if r["cohesion_pa"] == cohesion and not is_experiment(r)),
            key=lambda r: -r["cell_m"],
        )
        figures = {
            "max_surface_speed_m_s": [r["surface_speed"]["max_m_s"] for r in runs],
            "angle_deg": [r["angle_deg"] for r in runs],
            "flux_over_thin_layer_mid": [
                r["flux"]["flux_over_thin_layer"][len(S_FRACTIONS) // 2] for r in runs
            ],
            "layer_depth_mid_m": [r["middle"]["layer_depth_mid_m"] for r in runs],
            "wall_gap_mean_m": [r["middle"]["wall_gap_mean_m"] for r in runs],
        }
        cells = [r["cell_m"] for r in runs]
        entry = {"cohesion_pa": cohesion, "cells_m": cells, "figures": {}}
        for name, values in figures.items():
            diffs = [b - a for a, b in zip(values[:-1], values[1:], strict=True)]
            order = None
            # an order only for differences of one sign that shrink (a converging figure)
            # from the last two differences
            if len(diffs) >= 2 and diffs[-2] * diffs[-1] > 0 and abs(diffs[-2]) > abs(diffs[-1]):
                ratio = math.sqrt(cells[-3] / cells[-1])
                order = math.log(abs(diffs[-2]) / abs(diffs[-1])) / math.log(ratio)
            entry["figures"][name] = {
                "values": values,
                "differences": diffs,
                "relative_differences": [
                    d / b if b else None for d, b in zip(diffs, values[1:], strict=True)
                ],
                "observed_order": order,
            }
        out.append(entry)
    return out


def plot(rows: list[dict], path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    s_line = np.linspace(-1, 1, 201)
    colours = {0.005: "tab:blue", 0.0035: "tab:orange", 0.0025: "tab:green", 0.00175: "tab:purple"}
    for ax, cohesion in zip(axes[: len(COHESIONS)], COHESIONS, strict=True):
        ax.plot(s_line, 1 - s_line**2, "k-", lw=1.5, label="ω (L² - s²)/2 (thin layer)")
        for r in rows:
            if r["cohesion_pa"] != cohesion or r.get("experiment") == "material":
                continue
            f = r["flux"]
            scale = 0.5 * r["omega_rad_s"] * r["half_chord_m"] ** 2
            band = "wall_band_cells" in r
            colour = "tab:red" if band else colours.get(r["cell_m"], "grey")
            name = f"{r['cell_m'] * 1000:g} mm" + (", wall band 0" if band else "")
            ax.plot(
                f["s_over_L"],
                np.array(f["flux_m2_s"]) / scale,
                "o-",
                color=colour,
                label=f"layer flux, {name}",
            )
            ax.plot(
                f["s_over_L"],
                np.array(f["rigid_bed_flux_m2_s"]) / scale,
                "x:",
                color=colour,
                label=f"rigid bed ω (r_e² - r_b²)/2, {name}",
            )
        ax.set_xlabel("s / L (uphill positive)")
        ax.set_ylabel("flux / (ω L² / 2)")
        ax.set_title(f"flux through the flowing layer, c = {cohesion:g} Pa")
        ax.set_ylim(0, 1.1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6.5, loc="lower center")
    ax = axes[2]
    for r in rows:
        if r.get("experiment") == "material":
            continue
        sp = r["surface_speed"]
        band = "wall_band_cells" in r
        colour = "tab:red" if band else colours.get(r["cell_m"], "grey")
        style = "-" if r["cohesion_pa"] == 0 else "--"
        ax.plot(
            np.array(sp["s_m"]) / r["half_chord_m"],
            sp["speed_m_s"],
            style,
            color=colour,
            label=f"c = {r['cohesion_pa']:g}, {r['cell_m'] * 1000:g} mm"
            + (", band 0" if band else ""),
        )
    ax.set_xlabel("s / L")
    ax.set_ylabel("downslope surface speed (m/s)")
    ax.set_title("surface speed (solid: c = 0, dashed: c = 87 Pa)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6.5)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buffer.getvalue())


def _pct(x) -> str:
    return "n/a" if x is None or x != x else f"{100 * x:+.1f} %"


def _abs_pct(x) -> str:
    return "n/a" if x is None or x != x else f"{100 * abs(x):.1f} %"


def _carried(row) -> str:
    """The share of the material the stored (clipped) fill holds, and the largest raw fill."""
    sol = row["solver"]
    if sol.get("fill_volume_m3") is None:
        return "n/a"
    share = sol["fill_volume_m3"] / sol["material_volume_m3"]
    return f"{100 * share:.1f} % ({sol['fill_clipped_max']:.2f})"


def _ratio(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _others(row) -> str:
    share = row["contention"]["other_cpu_share"]
    return "n/a" if share is None else f"{100 * share:.0f} %"


def tables(rows: list[dict], conv: list[dict]) -> tuple[str, str, str, str]:
    main_rows, flux_rows, cost_rows = [], [], []
    for r in rows:
        name = r["case"]
        mm = f"{r['cell_m'] * 1000:g}"
        m = r["middle"]
        sv = r["surface_speed"]
        sol = r["solver"]
        main_rows.append(
            [
                name,
                mm,
                f"{r['angle_deg']:.2f}",
                f"{r['angle_deg'] - PHI_DEG:+.2f}",
                f"{r['surface_rms_residual_m'] * 1000:.2f} ({r['surface_rms_residual_cells']:.2f})",
                f"{r['surface_max_residual_m'] * 1000:.2f}",
                f"{r['chord_offset_m'] * 1000:+.1f}",
                f"{sv['max_m_s']:.4f}",
                f"{m['layer_depth_mid_m'] * 1000:.1f}",
                f"{m['wall_gap_mean_m'] * 1000:.1f}",
                f"{sol['periodicity_vx']:.3f} / {sol['periodicity_vy']:.3f}",
                f"{sol['periodicity_vx_norm']:.3f} / {sol['periodicity_vy_norm']:.3f}",
                _pct(r["particle_volume_growth"]),
                _carried(r),
                _ratio(sol.get("occupied_volume_over_seeded")),
            ]
        )
        f = r["flux"]
        flux_rows.append(
            [name, mm]
            + [_pct(v - 1) for v in f["flux_over_thin_layer"]]
            + [
                _abs_pct(m["flux_error_rigid_bed_max"]),
                _abs_pct(m["mass_balance_error_max"]),
            ]
        )
        sol = r["solver"]
        cost_rows.append(
            [
                name,
                mm,
                sol["particles"],
                sol["steps"],
                f"{sol['dt_last_s'] * 1e3:.3f}",
                f"{r['wall_s']:.1f}",
                f"{sol['particle_updates_per_s'] / 1e6:.2f}",
                _others(r),
            ]
        )
    t_main = table(
        [
            "case",
            "cell mm",
            "angle °",
            "angle - φ",
            "flat: rms mm (cells)",
            "flat: max mm",
            "chord offset mm",
            "max surface speed m/s",
            "layer depth mm (s=0)",
            "wall gap mm",
            "periodicity eq.30 vx / vy",
            "periodicity norm vx / vy",
            "Σ vol / Σ vol0 - 1",
            "fill holds (largest raw)",
            "spacing vol / seeded",
        ],
        main_rows,
    )
    t_flux = table(
        ["case", "cell mm"]
        + [f"s/L={v:+.1f}" for v in S_FRACTIONS]
        + [f"max vs rigid bed, |s/L|≤{MIDDLE}", f"max up/down - 1, |s/L|≤{MIDDLE}"],
        flux_rows,
    )
    t_cost = table(
        [
            "case",
            "cell mm",
            "particles",
            "steps",
            "dt ms",
            "wall s",
            "M particle upd/s",
            "others' CPU",
        ],
        cost_rows,
    )
    conv_rows = []
    for entry in conv:
        for name, fig in entry["figures"].items():
            vals = fig["values"]
            scale = 1000.0 if name.endswith("_m") else 1.0
            conv_rows.append(
                [
                    f"c = {entry['cohesion_pa']:g} Pa",
                    name,
                    " / ".join(f"{v * scale:.4g}" for v in vals),
                    " / ".join(f"{d * scale:+.3g}" for d in fig["differences"]),
                    " / ".join(_pct(d) for d in fig["relative_differences"]),
                    "n/a" if fig["observed_order"] is None else f"{fig['observed_order']:.2f}",
                ]
            )
    t_conv = table(
        [
            "case",
            "figure (lengths in mm)",
            " / ".join(f"{c * 1000:g}" for c in CELLS) + " mm",
            "differences",
            "relative",
            "order (last two)",
        ],
        conv_rows,
    )
    return t_main, t_flux, t_cost, t_conv


def _thin_layer_terms(r: dict) -> dict:
    """At s = 0: the thin-layer deficit split into rigid rotation's share of the layer's
    depth and of the bed's gap from the wall (fractions of ω L² / 2)."""
    k = len(S_FRACTIONS) // 2
    f = r["flux"]
    big_l2 = r["half_chord_m"] ** 2
    d = r["chord_offset_m"]
    delta = f["layer_depth_m"][k]
    gap = f["wall_gap_m"][k]
    radius = math.sqrt(big_l2 + d * d)
    return {
        "measured": f["flux_over_thin_layer"][k] - 1.0,
        "layer_depth": -((d - delta) ** 2 - d * d) / big_l2,
        "wall_gap": -(radius**2 - (radius - gap) ** 2) / big_l2,
    }


def findings(rows: list[dict], conv: list[dict]) -> str:
    """The figures that matter, in words (computed from the runs)."""
    lines = []
    plain = [r for r in rows if not is_experiment(r)]
    for cohesion in COHESIONS:
        runs = sorted(
            (r for r in plain if r["cohesion_pa"] == cohesion), key=lambda r: -r["cell_m"]
        )
        for r in runs:
            m = r["middle"]
            terms = _thin_layer_terms(r)
            lines.append(
                f"- c = {cohesion:g} Pa, {r['cell_m'] * 1000:g} mm: angle {r['angle_deg']:.2f}° "
                f"({r['angle_deg'] - PHI_DEG:+.2f}° from φ), surface rms "
                f"{r['surface_rms_residual_cells']:.2f} cells; layer flux / ω (L² - s²)/2 in "
                f"|s/L| ≤ {MIDDLE}: mean {_pct(m['flux_error_thin_layer_mean'])}, worst "
                f"{_abs_pct(m['flux_error_thin_layer_max'])}; at s = 0 {_pct(terms['measured'])}, "
                f"of which rigid rotation assigns {_pct(terms['layer_depth'])} to the "
                f"{m['layer_depth_mid_m'] * 1000:.1f} mm depth of the downslope layer and "
                f"{_pct(terms['wall_gap'])} to the bed's edge standing "
                f"{r['flux']['wall_gap_m'][len(S_FRACTIONS) // 2] * 1000:.1f} mm off the wall; "
                f"against the rigid-bed balance with the measured edge and base: worst "
                f"{_abs_pct(m['flux_error_rigid_bed_max'])}."
            )
    for entry in conv:
        fig = entry["figures"]["max_surface_speed_m_s"]
        v, d, order = fig["values"], fig["differences"], fig["observed_order"]
        cells = entry["cells_m"]
        text = (
            f"- Largest surface speed, c = {entry['cohesion_pa']:g} Pa: "
            + " / ".join(f"{x:.3f}" for x in v)
            + " m/s at "
            + " / ".join(f"{c * 1000:g}" for c in cells)
            + " mm, successive changes "
            + " and ".join(f"{x:+.4f}" for x in d)
            + " m/s"
        )
        if order is not None and order > 0.5:
            ratio = cells[-2] / cells[-1]
            limit = v[-1] + d[-1] / (ratio**order - 1.0)
            text += (
                f": converging at observed order {order:.2f} (Richardson estimate of the "
                f"limit {limit:.3f} m/s)."
            )
        else:
            text += (
                ": not converged (the changes do not shrink; at first order they would "
                "shrink by 1.41 per step)."
            )
        lines.append(text)
    for r in plain:
        if r["surface_rms_residual_cells"] > 0.5:
            lines.append(
                f"- c = {r['cohesion_pa']:g} Pa, {r['cell_m'] * 1000:g} mm: the surface is not "
                f"flat (a line misses it by {r['surface_max_residual_m'] * 1000:.1f} mm at "
                f"worst, rms {r['surface_rms_residual_m'] * 1000:.1f} mm): the rolling-drum "
                "relations, which assume a flat surface, are only indicative there."
            )
    for r in (r for r in rows if r.get("experiment") == "material"):
        m, terms = r["middle"], _thin_layer_terms(r)
        lines.append(
            f"- Experiment, {r['case']}, {r['cell_m'] * 1000:g} mm: chord offset "
            f"{r['chord_offset_m'] * 1000:+.1f} mm, largest raw fill "
            f"{r['solver']['fill_clipped_max']:.2f}, layer {m['layer_depth_mid_m'] * 1000:.1f} mm "
            f"deep, bed edge {m['wall_gap_mean_m'] * 1000:.1f} mm off the wall; layer flux / "
            f"ω (L² - s²)/2 mean {_pct(m['flux_error_thin_layer_mean'])}, worst "
            f"{_abs_pct(m['flux_error_thin_layer_max'])} in |s/L| ≤ {MIDDLE} (at s = 0 "
            f"{_pct(terms['measured'])}: layer depth {_pct(terms['layer_depth'])}, wall gap "
            f"{_pct(terms['wall_gap'])}); against the rigid-bed balance: worst "
            f"{_abs_pct(m['flux_error_rigid_bed_max'])}."
        )
    band = next((r for r in rows if "wall_band_cells" in r), None)
    if band is not None:
        m = band["middle"]
        lines.append(
            f"- Experiment, c = 0, {band['cell_m'] * 1000:g} mm with the wall band at 0 "
            f"instead of {band['default_wall_band_cells']:g} cells: bed edge "
            f"{m['wall_gap_mean_m'] * 1000:.1f} mm off the wall, layer flux / ω (L² - s²)/2 "
            f"mean {_pct(m['flux_error_thin_layer_mean'])}, angle {band['angle_deg']:.2f}°, "
            f"periodicity (eq. 30, vx) {band['solver']['periodicity_vx']:.3f}."
        )
    return "\n".join(lines)


def measure() -> dict:
    quiet = wait_for_quiet()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    started = time.perf_counter()
    FlowSimulation(scene(0.02, 0.0)).run(max_steps=25, progress=False)  # compile or load
    echo(f"warm-up {time.perf_counter() - started:.1f} s")
    rows = []
    for cohesion in COHESIONS:
        for cell in CELLS:
            row = run_case(cell, cohesion)
            rows.append(row)
            echo(
                f"c = {cohesion:g} Pa, {cell * 1000:g} mm: angle {row['angle_deg']:.2f}°, "
                f"flux/thin (s=0) {row['flux']['flux_over_thin_layer'][3]:.3f}, "
                f"max surface speed {row['surface_speed']['max_m_s']:.4f} m/s, "
                f"wall {row['wall_s']:.0f} s"
            )
    if VARIANT["name"] == "flow_drum":  # the experiments belong to the default model
        band = wall_band_experiment(CELLS[0])
        if band is not None:
            rows.append(band)
        rows.extend(material_experiments())
    payload = {
        "benchmark": VARIANT["name"],
        "variant": VARIANT,
        "machine": info,
        "settings": {
            "diameter_m": DIAMETER,
            "rpm": RPM,
            "fill_fraction": FILL,
            "cohesions_pa": COHESIONS,
            "cells_m": CELLS,
            "stiffness_scaling": STIFFNESS_SCALING,
            "settle_time_s": SETTLE_S,
            "revolutions": REVOLUTIONS,
            "friction_angle_deg": PHI_DEG,
            "material_experiments": {
                "cell_m": MATERIAL_CELL,
                "stiffness_scaling_and_dilation_deg": MATERIAL_CASES,
            },
            "s_over_L": S_FRACTIONS,
            "middle_s_over_L": MIDDLE,
            "definitions": {
                "flux": "downslope flux of fill*v along the normal to the surface line, "
                "from above the surface to where it turns uphill (m2/s)",
                "thin_layer_flux": "omega (L^2 - s^2) / 2, DESIGN section 7",
                "rigid_bed_flux": "omega (r_e^2 - r_b^2) / 2, r_e the bed's outer edge "
                "(fill = 0.5), r_b the base of the downslope motion, on the same line",
                "wall_time": "single run, wall clock; the machine is shared",
            },
        },
        "runs": rows,
        "convergence": convergence(rows),
        "total_s": time.perf_counter() - started,
        "load_average_at_end": load_average(),
        "cpu_pressure_at_end": cpu_pressure(),
    }
    path = write_json(VARIANT["name"], payload)
    echo(f"wrote {path.relative_to(path.parents[2])}")
    return payload


def render(payload: dict) -> None:
    """Print the tables and write flow_drum.md and flow_drum.png from the results."""
    info, rows, conv = payload["machine"], payload["runs"], payload["convergence"]
    t_main, t_flux, t_cost, t_conv = tables(rows, conv)
    text_findings = findings(rows, conv)
    for title, text in (
        ("Surface, layer, periodicity", t_main),
        ("Layer flux / ω (L² - s²)/2 - 1", t_flux),
        ("Convergence with the cell", t_conv),
        ("Cost", t_cost),
    ):
        echo()
        echo(f"## {title}")
        echo()
        echo(text)
    echo()
    echo(text_findings)

    cells_mm = " / ".join(f"{c * 1000:g}" for c in CELLS)
    name = VARIANT["name"]
    md = f"""<!-- written by benchmarks/flow_drum.py -->
# Rolling drum (2-D) with the built-in flow solver{VARIANT["note"]}

Machine: {machine_line(info)}. Whole script {payload["total_s"]:.0f} s.

The machine is shared with other work: wall times and particle updates per second are
indicative only (the column "others' CPU" says how much other processes took; the solver
runs these small 2-D beds on one thread). The accuracy figures (angle, flatness, flux,
surface speed) do not depend on the load.

Scene: drum {DIAMETER * 1000:g} mm across, `fill.fraction = {FILL}`, {RPM:g} rpm, Table 1
material (φ = {PHI_DEG}°, μw = 0.324) with E / {STIFFNESS_SCALING:g}
(`solver.stiffness_scaling`; see `flow_stiffness.md` for its error), settled
{SETTLE_S} s, {REVOLUTIONS} revolutions, lab-frame average of the last one. Diagnostics:
`blendxr.flow.diagnostics` (surface at fill = 0.5 along normals, middle 80 % of the
chord; flux of fill·v along the normal from above the surface to where the motion turns
uphill; surface speed = fill-weighted velocity at the local fill = 0.5 point).

![flux through the layer and surface speed]({name}.png)

## Surface, layer, periodicity

"chord offset": signed distance of the surface line from the axis (0 for a half-full
drum whose material keeps its volume). "layer depth": distance from the surface to
where the lab-frame motion turns uphill, at s = 0. "wall gap": distance from the bed's
outer edge (fill = 0.5) to the wall along the normal lines, mean over |s/L| ≤ {MIDDLE}.
Periodicity: the solver's eq. (30) attributes between revolutions 1 and 2 (the first
includes the start from rest). "Σ vol / Σ vol0 - 1": the particles' current volumes
(J times the seeded ones) over the seeded ones at the end of the run; the fill counts
the seeded volumes, so this drift shows only in the stress update and the positions.
"fill holds": the share of the material's volume that the stored fill holds after
clipping at 1, with the largest phase-averaged fill before clipping (cells whose
particles crowd past their seeded packing); "spacing vol / seeded": the volume the
particles take by their spacing at the end of the run over their seeded volume
(`occupied_volume_over_seeded`; below 1 for a bed that compacted).

{t_main}

## Flux through the flowing layer

Layer flux / ω (L² - s²)/2 - 1 at each s/L (DESIGN §7, thin-layer limit), and the
largest deviation in |s/L| ≤ {MIDDLE} from the rigid-bed balance ω (r_e² - r_b²)/2 (r_e:
distance of the bed's outer edge from the axis, r_b: of the base of the downslope
motion, both on the same normal line) and between the upslope flux below the layer and
the layer's flux (mass balance of the averaged field).

{t_flux}

## Convergence with the cell

Values at {cells_mm} mm, differences between successive cells, and the observed order
log(|d1| / |d2|) / log(1.41) from the last two differences, when they have the same sign and shrink.

{t_conv}

## Cost

{t_cost}

## Findings

{text_findings}
"""
    write_atomic(RESULTS / f"{name}.md", md)
    plot(rows, RESULTS / f"{name}.png")
    echo()
    echo(f"wrote {name}.md, {name}.png")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--report",
        action="store_true",
        help="only rewrite flow_drum.md and flow_drum.png from results/flow_drum.json",
    )
    parser.add_argument(
        "--projection",
        type=int,
        metavar="N",
        help="the cohesionless cell study with solver.density_projection = N and no "
        "dilation, into flow_drum_projection.{json,md,png}",
    )
    parser.add_argument(
        "--mu-i",
        dest="mu_i",
        action="store_true",
        help="with --projection: the mu(I) friction on too (material.friction_angle_limit_deg "
        "= 37.7 with 1 mm grains, as flow_work_precision.py's runs), into *_mu_i.*",
    )
    parser.add_argument(
        "--keep-dilation",
        dest="keep_dilation",
        action="store_true",
        help="with --projection: keep the scene's dilation angle, into *_dilation.*",
    )
    args = parser.parse_args(argv)
    if args.projection:
        global COHESIONS
        COHESIONS = (0.0,)
        VARIANT.update(
            # every 10 steps is the reference; another period gets its own files
            name="flow_drum_projection" + ("" if args.projection == 10 else str(args.projection)),
            solver={"density_projection": args.projection},
            material={"dilation_angle_deg": 0.0},
            note=f": density projection every {args.projection} steps, no dilation",
        )
        if args.keep_dilation:
            VARIANT["material"].pop("dilation_angle_deg")
            VARIANT["name"] += "_dilation"
            VARIANT["note"] = VARIANT["note"].replace("no dilation", "the default dilation")
        if args.mu_i:
            VARIANT["name"] += "_mu_i"
            # with 1 mm grains, as flow_work_precision.py's mu(I) runs (the control)
            VARIANT["material"]["friction_angle_limit_deg"] = 37.7
            VARIANT["material"]["particle_diameter"] = 0.001
            VARIANT["note"] += ", mu(I) friction"
    if args.report:
        payload = json.loads((RESULTS / f"{VARIANT['name']}.json").read_text())
    else:
        payload = measure()
    render(payload)


if __name__ == "__main__":
    main()
