"""The error of the answer against its cost: revolutions to a uniform blend.

A user asks how many revolutions a blend needs to reach RSD 0.1 or 0.05. This benchmark
measures how far that answer, and the RSD curve behind it, moves with every choice the
user (or a scene) makes: the flow cell, the flow solver's time step (Courant number), the
ADE cells, the scheme, the stiffness scaling
(an unscaled run at a coarse cell), rate-independent Mohr-Coulomb against the optional
mu(I) friction, the revolution of the flow that is repeated (2 against 3, and an average
over three), and the density projection with no dilation (the defaults) against the
flow without them. Each
case records its wall time (flow solve and mixing separately; a cached flow keeps the
time of its solve), so the table is a work-precision table.

Groups: each group varies one choice of a base scene; its reference is the group's
finest (or most faithful) member, named in ``GROUPS``. The error of a case is
``|dN|`` (revolutions to RSD 0.1 and 0.05 against the reference's) and the largest
relative difference of its RSD curve from the reference's over the revolutions run.

Bases: ``tote-small`` (the quick default: 20 mm flow cell, E/100, 60 ADE cells) and the
paper's four Tote cases (``tote-40-top-bottom`` ...: 7.5 mm, E/10, 100 ADE cells).
Flows are cached (``$BLENDXR_CACHE``, default ``runs/cache`` in the checkout), so the
top-bottom and side-side cases of one fill solve their flow once, and a rerun of a case
re-solves nothing.

Run: ``python benchmarks/answer_precision.py [--case NAME ...]``; writes
``benchmarks/results/answer_precision.{json,md}`` and ``answer_precision.png`` (the RSD
curves of each group, and error against cost). Cases are listed with ``--help``.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "2")

import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _common import RESULTS, echo, flow_cache, machine_line, run_cases, table  # noqa: E402

NAME = "answer_precision"
LEVELS = (0.2, 0.1, 0.05)
#: Every case mixes until its RSD is below the last level (or this many revolutions), so
#: that N(0.05) is an interpolation, not "not reached".
STUDY_MIXING = {"mixing.revolutions": 40, "mixing.stop_rsd": 0.04}
#: the segregation intensity whose time is reported beside the time to the floor
INTENSITY_LEVEL = 0.1
MU_I = {"material.friction_angle_limit_deg": 37.7}  # docs/flow.md: the drum's mu(I) runs

#: group -> (base scene, {member: dotted overrides}, reference member)
GROUPS = {
    "small_flow_cell": (
        "tote-small",
        {
            "20mm": {},
            "15mm": {"flow.cell": 0.015},
            "12.5mm": {"flow.cell": 0.0125},
            "10mm": {"flow.cell": 0.01},
            "7.5mm": {"flow.cell": 0.0075},
        },
        "7.5mm",
    ),
    # the same study on the flow with the density projection and psi = 0 (the defaults
    # since), its fill deposited with B-splines: does the answer converge now?
    "small_flow_cell_cured": (
        "tote-small",
        {
            "20mm": {},
            "15mm": {"flow.cell": 0.015},
            "10mm": {"flow.cell": 0.01},
            "7.5mm": {"flow.cell": 0.0075},
        },
        "7.5mm",
    ),
    "small_ade_cells": (
        "tote-small",
        {
            "40": {"numerics.cells": 40},
            "60": {},
            "100": {"numerics.cells": 100},
            "150": {"numerics.cells": 150},
        },
        "150",
    ),
    "small_scheme": (
        "tote-small",
        {
            "finite-volume": {},
            "lax-wendroff": {"numerics.scheme": "lax-wendroff"},
            "finite-volume_100": {"numerics.cells": 100},
            "finite-volume_150": {"numerics.cells": 150},
            "lax-wendroff_100": {"numerics.cells": 100, "numerics.scheme": "lax-wendroff"},
            "lax-wendroff_150": {"numerics.cells": 150, "numerics.scheme": "lax-wendroff"},
            "semi-lagrangian": {"numerics.scheme": "semi-lagrangian"},
            "semi-lagrangian_100": {"numerics.cells": 100, "numerics.scheme": "semi-lagrangian"},
            "semi-lagrangian_150": {"numerics.cells": 150, "numerics.scheme": "semi-lagrangian"},
            # the two cheaper schemes finer than finite volume can afford: do they meet,
            # as they do on the drum at 800 cells?
            "lax-wendroff_200": {"numerics.cells": 200, "numerics.scheme": "lax-wendroff"},
            "lax-wendroff_250": {"numerics.cells": 250, "numerics.scheme": "lax-wendroff"},
            "semi-lagrangian_200": {"numerics.cells": 200, "numerics.scheme": "semi-lagrangian"},
            "semi-lagrangian_250": {"numerics.cells": 250, "numerics.scheme": "semi-lagrangian"},
        },
        "finite-volume_100",
    ),
    "small_stiffness": (
        "tote-small",
        {
            "E/100": {},
            "E/10": {"solver.stiffness_scaling": 10.0},
            "E": {"solver.stiffness_scaling": 1.0},
        },
        "E",
    ),
    "small_rheology": (
        "tote-small",
        {"mohr-coulomb": {}, "mu(I)": MU_I},
        "mohr-coulomb",
    ),
    "small_revolution": (
        "tote-small",
        {
            "rev2": {},
            "rev3": {"solver.revolutions": 3},
            "avg3": {
                "solver.revolutions": 6,
                "solver.average_revolutions": 3,
                "material.dilation_angle_deg": 0.0,
            },
            "rev3_psi0": {"solver.revolutions": 3, "material.dilation_angle_deg": 0.0},
        },
        "avg3",
    ),
    "small_projection": (
        # the defaults (density projection, no dilation) against the flow before them
        "tote-small",
        {
            "default": {},
            "no_projection_psi0.1": {
                "solver.density_projection": 0,
                "material.dilation_angle_deg": 0.1,
            },
            "no_projection": {"solver.density_projection": 0},
        },
        "default",
    ),
}
#: The calibration drum's ADE settings the drum groups run at, named here rather than
#: taken from the scene so that a group keeps its meaning when the scene's default moves:
#: the finite-volume 100 cells it shipped with, and the setting the scheme group chose.
DRUM_OLD_DEFAULT = {"numerics.scheme": "finite-volume", "numerics.cells": 100}
LOW_DIFFUSION = {"numerics.scheme": "lax-wendroff", "numerics.cells": 400}
DRUM_FLOW_CELLS = {
    "5mm": {"flow.cell": 0.005},
    "3.5mm": {"flow.cell": 0.0035},
    "2.5mm": {},
    "1.75mm": {"flow.cell": 0.00175},
}


def _drum_k1(setting: dict, k1s) -> dict:
    """Members ``"<k1>"`` of a k1 group at one ADE setting."""
    return {f"{k1:g}": {**setting, "mixing.k1": k1} for k1 in k1s}


# the calibration drum with the solver's flow: does k1 move the time to the floor? Then at
# twice the ADE resolution (does k1 matter more once the scheme's own diffusion is
# halved?), and with the less diffusive setting
GROUPS["drum_k1"] = (
    "drum-calibration",
    _drum_k1(DRUM_OLD_DEFAULT, (0.0, 0.005, 0.01, 0.02)),
    "0.01",
)
GROUPS["drum_k1_200cells"] = (
    "drum-calibration",
    _drum_k1({**DRUM_OLD_DEFAULT, "numerics.cells": 200}, (0.0, 0.01, 0.02)),
    "0.01",
)
GROUPS["drum_k1_lw400"] = (
    "drum-calibration",
    _drum_k1(LOW_DIFFUSION, (0.0, 0.005, 0.01, 0.02, 0.04)),
    "0.01",
)
GROUPS["drum_ade_cells"] = (
    "drum-calibration",
    {f"{n}": {**DRUM_OLD_DEFAULT, "numerics.cells": n} for n in (100, 200, 400)},
    "400",
)
GROUPS["drum_scheme"] = (
    # the drum's time to the floor rises with the ADE cells (numerical diffusion blurs
    # its spiral's bands): does a less diffusive scheme converge sooner?
    "drum-calibration",
    {
        f"{scheme}_{cells}": {"numerics.scheme": scheme, "numerics.cells": cells}
        for scheme in ("finite-volume", "lax-wendroff", "semi-lagrangian")
        for cells in (100, 200, 400, 800)
    },
    "semi-lagrangian_800",
)
# the drum's answer against the flow cell (the drum half of the flow issue's
# convergence), at the old and at the less diffusive ADE setting
GROUPS["drum_flow_cell"] = (
    "drum-calibration",
    {m: {**DRUM_OLD_DEFAULT, **v} for m, v in DRUM_FLOW_CELLS.items()},
    "1.75mm",
)
GROUPS["drum_flow_cell_lw400"] = (
    "drum-calibration",
    {m: {**LOW_DIFFUSION, **v} for m, v in DRUM_FLOW_CELLS.items()},
    "1.75mm",
)
# the same without shear diffusion: what the flow's advection and the scheme mix alone,
# and whether the finest flow's late plateau comes from the flow or from k1
GROUPS["drum_flow_cell_lw400_k1_0"] = (
    "drum-calibration",
    {m: {**LOW_DIFFUSION, **v, "mixing.k1": 0.0} for m, v in DRUM_FLOW_CELLS.items()},
    "1.75mm",
)
# the same two with the steady flow's divergence kept as stored: what the projection
# (numerics.steady_divergence) does to the answer at each flow cell
GROUPS["drum_flow_cell_lw400_kept"] = (
    "drum-calibration",
    {
        m: {**LOW_DIFFUSION, **v, "numerics.steady_divergence": "keep"}
        for m, v in DRUM_FLOW_CELLS.items()
    },
    "1.75mm",
)
GROUPS["drum_flow_cell_lw400_k1_0_kept"] = (
    "drum-calibration",
    {
        m: {**LOW_DIFFUSION, **v, "mixing.k1": 0.0, "numerics.steady_divergence": "keep"}
        for m, v in DRUM_FLOW_CELLS.items()
    },
    "1.75mm",
)
for _case in ("tote-40-top-bottom", "tote-40-side-side", "tote-60-top-bottom",
              "tote-60-side-side"):  # fmt: skip
    GROUPS[f"{_case}_flow_cell"] = (
        _case,
        {
            "20mm": {"flow.cell": 0.02},
            "15mm": {"flow.cell": 0.015},
            "10mm": {"flow.cell": 0.01},
            "7.5mm": {},
        },
        "7.5mm",
    )
    GROUPS[f"{_case}_ade_cells"] = (
        _case,
        {"60": {"numerics.cells": 60}, "100": {}, "150": {"numerics.cells": 150}},
        "150",
    )

# the paper's rate-independent Mohr-Coulomb against the optional mu(I) friction on the
# paper's 40 % top-bottom case, at 10 mm (the Mohr-Coulomb member shares its flow with
# the flow-cell group's 10 mm member)
GROUPS["tote-40-top-bottom_rheology"] = (
    "tote-40-top-bottom",
    {"mohr-coulomb_10mm": {"flow.cell": 0.01}, "mu(I)_10mm": {"flow.cell": 0.01, **MU_I}},
    "mohr-coulomb_10mm",
)

# the revolution of the flow that is repeated, on the paper's 40 % top-bottom case at
# 10 mm: the second against the third (the scenes' default, shared with the flow-cell
# group's 10 mm member) and the average over revolutions 3-5 (eq. (30) against 0-2 needs
# revolutions >= 2 x 3, so six are turned)
for _case in ("tote-40-top-bottom", "tote-60-top-bottom"):
    GROUPS[f"{_case}_revolution"] = (
        _case,
        {
            "rev2_10mm": {"flow.cell": 0.01, "solver.revolutions": 2},
            "rev3_10mm": {"flow.cell": 0.01},
            "avg4-6_10mm": {
                "flow.cell": 0.01,
                "solver.revolutions": 6,
                "solver.average_revolutions": 3,
            },
        },
        "avg4-6_10mm",
    )

# the flow solver's time step (solver.courant; dt = courant h / (c_p + |v|max)) on the
# paper's 40 % top-bottom case at 10 mm: 0.2, 0.4 (the scenes' default, shared with the
# flow-cell group's 10 mm member) and 0.8, against the smallest step
GROUPS["tote-40-top-bottom_courant_10mm"] = (
    "tote-40-top-bottom",
    {
        f"courant{c:g}_10mm": {"flow.cell": 0.01, **({} if c == 0.4 else {"solver.courant": c})}
        for c in (0.2, 0.4, 0.8)
    },
    "courant0.2_10mm",
)

# the spin-up revolution at twice the step (solver.spin_up_courant = 0.8, off by default)
# on the paper's 40 % top-bottom case at its own 7.5 mm: does the kept third revolution,
# and so the answer, keep the default's? (the default member shares its flow with the
# flow-cell group's 7.5 mm member)
GROUPS["tote-40-top-bottom_spin_up"] = (
    "tote-40-top-bottom",
    {"default_7.5mm": {}, "spin_up0.8_7.5mm": {"solver.spin_up_courant": 0.8}},
    "default_7.5mm",
)

# the scheme and ADE cells on a paper case's flow (60 % top-bottom, 10 mm, the mean of
# revolutions 4-6, shared with the revolution group): do the schemes meet there as
# they do on tote-small?
_AVG = GROUPS["tote-60-top-bottom_revolution"][1]["avg4-6_10mm"]
GROUPS["tote-60-top-bottom_scheme"] = (
    "tote-60-top-bottom",
    {
        "finite-volume_100": _AVG,
        "semi-lagrangian_100": {**_AVG, "numerics.scheme": "semi-lagrangian"},
        "semi-lagrangian_150": {
            **_AVG,
            "numerics.scheme": "semi-lagrangian",
            "numerics.cells": 150,
        },
        "semi-lagrangian_200": {
            **_AVG,
            "numerics.scheme": "semi-lagrangian",
            "numerics.cells": 200,
        },
        "lax-wendroff_200": {**_AVG, "numerics.scheme": "lax-wendroff", "numerics.cells": 200},
        "lax-wendroff_250": {**_AVG, "numerics.scheme": "lax-wendroff", "numerics.cells": 250},
    },
    # the finest member of the one sequence whose answer settles as its cells shrink
    "semi-lagrangian_200",
)

CASES = {
    f"{group}:{member}": (base, values)
    for group, (base, members, _) in GROUPS.items()
    for member, values in members.items()
}


def _run_key(case: str) -> str:
    """What makes a run: its base scene and values (a case's name is not part of it)."""
    base, values = CASES[case]
    return json.dumps([base, values], sort_keys=True)


#: Cases by the run they are: members of several groups that are one run share a result.
SAME_RUN: dict[str, list[str]] = {}
for _name in CASES:
    SAME_RUN.setdefault(_run_key(_name), []).append(_name)


def _result(cases: dict, case: str) -> dict | None:
    """The result of a case, or of another case that is the same run."""
    for name in [case, *SAME_RUN[_run_key(case)]]:
        if name in cases:
            return cases[name]
    return None


def run_case(case: str) -> dict:
    """Flow (cached) and mixing of one case; the answer and what it cost."""
    import blendxr as bx
    from blendxr import pipeline

    base, values = CASES[case]
    scene = bx.load_scene(base, {**STUDY_MIXING, **values})
    stages = pipeline.Stages()
    with stages.measure("flow"):
        flow, source = pipeline.scene_flow(scene, cache=flow_cache(), progress=False)
    with stages.measure("mixing"):
        mixed = bx.mix(flow, scene, progress=False)
    summary = pipeline.mixing_summary(mixed, LEVELS)
    flow_info = pipeline.flow_summary(flow)
    floor = summary["random_mixture_intensity"]
    to_floor = to_intensity = intensity = None
    if floor is not None:
        revolution, intensity = mixed["revolution"].values, mixed["intensity"].values
        to_floor = pipeline.revolutions_to_level(revolution, intensity, floor)
        # a level well above the floor: where a curve flattens just above its floor, the
        # time to the floor is ill-conditioned and this one is not
        to_intensity = pipeline.revolutions_to_level(revolution, intensity, INTENSITY_LEVEL)
        intensity = [None if not np.isfinite(v) else float(v) for v in intensity]
    return {
        "base": base,
        "values": values,
        "flow_key": source.key,
        "flow_wall_s": float(flow.attrs.get("wall_time_s", math.nan)),
        "flow_cache": source.cache,
        "density_projection_every": int(flow.attrs.get("density_projection_every", 0)),
        "mix_wall_s": stages.records["mixing"]["wall_s"],
        "mix_peak_mb": stages.records["mixing"]["peak_memory_mb"],
        "revolutions_to_rsd": summary["revolutions_to_rsd"],
        "final_rsd": summary["final_rsd"],
        "final_intensity": summary["final_intensity"],
        "random_mixture_rsd": summary["random_mixture_rsd"],
        "random_mixture_intensity": floor,
        "revolutions_to_intensity_floor": to_floor,
        f"revolutions_to_intensity_{INTENSITY_LEVEL:g}": to_intensity,
        "intensity": intensity,
        "periodicity_eq30": flow_info.get("periodicity_eq30"),
        "fill_share": flow_info.get("fill_share"),
        "revolution": mixed["revolution"].values.tolist(),
        "rsd": mixed["rsd"].values.tolist(),
        "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def _errors(result: dict, reference: dict | None) -> dict:
    """|dN| at each level and the largest relative RSD difference from the reference."""
    if reference is None:
        return {}
    out = {}
    for level in LEVELS:
        key = f"{level:g}"
        a, b = result["revolutions_to_rsd"].get(key), reference["revolutions_to_rsd"].get(key)
        out[key] = abs(a - b) if a is not None and b is not None else None
    ra, rb = np.asarray(result["revolution"]), np.asarray(reference["revolution"])
    common = np.intersect1d(np.round(ra, 9), np.round(rb, 9))
    if len(common):
        va = np.interp(common, ra, result["rsd"])
        vb = np.interp(common, rb, reference["rsd"])
        out["rsd_curve"] = float(np.max(np.abs(va / vb - 1.0)))
    return out


def _fmt_rev(value) -> str:
    return "not reached" if value is None else f"{value:.2f}"


def _fmt_err(value) -> str:
    return "" if value is None else f"{value:.2f}"


def _fmt_floor(result: dict) -> str:
    """Revolutions to the random-mixture intensity (blank where no intensity is defined)."""
    if result.get("random_mixture_intensity") is None or result.get("final_intensity") is None:
        return ""
    return _fmt_rev(result.get("revolutions_to_intensity_floor"))


def _fmt_intensity_level(result: dict) -> str:
    """Revolutions to INTENSITY_LEVEL (blank where the run did not record it)."""
    key = f"revolutions_to_intensity_{INTENSITY_LEVEL:g}"
    if key not in result or result.get("intensity") is None:
        return ""
    return _fmt_rev(result[key])


#: The first study run made on the cured flow (projection and B-spline fill defaults);
#: results from before the flow's ``density_projection_every`` was recorded are dated.
CURED_SINCE = "2026-12-03 13:45:00"


def _flow_state(result: dict) -> str:
    """The flow solver's defaults the case ran on: "cured", "before" or "no projection"."""
    every = result.get("density_projection_every")
    if every is not None:
        return "cured" if every > 0 else "no projection"
    return "cured" if result.get("finished", "") >= CURED_SINCE else "before"


def report(cases: dict, machine: dict) -> str:
    lines = [
        "# The error of the answer against its cost",
        "",
        f"Latest run's machine: {machine_line(machine)}. "
        "`benchmarks/answer_precision.py`. Each case names the processor it ran on "
        '(column "cpu"): times from different processors differ by up to 2x.',
        "",
        "N(x): revolutions to RSD x (log-linear between records every 0.25 revolution); "
        "|dN|: against the group's reference (marked *); curve: the largest relative "
        "difference of the RSD curve from the reference's. N(I_R): revolutions to the "
        "random-mixture segregation intensity of the sampling cells (where one is defined), "
        f"N(I {INTENSITY_LEVEL:g}): to that intensity (runs that recorded it). "
        "Flow s: the solve's wall time "
        "(a cached flow keeps it); mix s: the mixing run.",
        "",
        'Column "flow": *cured* where the case ran on the flow solver as it now is '
        "(density projection, ψ = 0, the fill deposited with B-splines; docs/flow.md), "
        "*before* where it ran before those became the defaults: such flows crowd past "
        "their packing as `flow_crowding.md` shows; `small_projection` measures what the "
        "change does to the answer.",
        "",
    ]
    for group, (base, members, ref) in GROUPS.items():
        done = {m: _result(cases, f"{group}:{m}") for m in members}
        if not any(done.values()):
            continue
        reference = done.get(ref)
        rows = []
        for member, result in done.items():
            if result is None:
                continue
            err = _errors(result, reference) if member != ref else {}
            p = result.get("periodicity_eq30") or {}
            rows.append(
                [
                    member + (" *" if member == ref else ""),
                    _fmt_rev(result["revolutions_to_rsd"]["0.1"]),
                    _fmt_rev(result["revolutions_to_rsd"]["0.05"]),
                    _fmt_err(err.get("0.1")),
                    _fmt_err(err.get("0.05")),
                    "" if "rsd_curve" not in err else f"{err['rsd_curve']:.1%}",
                    f"{result['final_rsd']:.4f}",
                    _fmt_floor(result),
                    _fmt_intensity_level(result),
                    " / ".join(f"{v:.0%}" for v in p.values()) if p else "",
                    "" if result.get("fill_share") is None else f"{result['fill_share']:.1%}",
                    f"{result['flow_wall_s']:.0f}",
                    f"{result['mix_wall_s']:.0f}",
                    _flow_state(result),
                    result.get("cpu", ""),
                ]
            )
        lines += [
            f"## {group} (base `{base}`)",
            "",
            table(
                [
                    "case",
                    "N(0.1)",
                    "N(0.05)",
                    "|dN| 0.1",
                    "|dN| 0.05",
                    "curve",
                    "final RSD",
                    "N(I_R)",
                    f"N(I {INTENSITY_LEVEL:g})",
                    "eq. 30",
                    "fill",
                    "flow s",
                    "mix s",
                    "flow",
                    "cpu",
                ],  # fmt: skip
                rows,
            ),
            "",
        ]
    return "\n".join(lines)


def summary(case: str, result: dict) -> str:
    n = result["revolutions_to_rsd"]
    return (
        f"{case}: N(0.1) {_fmt_rev(n['0.1'])}, N(0.05) {_fmt_rev(n['0.05'])}, final RSD "
        f"{result['final_rsd']:.4f}; flow {result['flow_wall_s']:.0f} s "
        f"({result['flow_cache']}), mix {result['mix_wall_s']:.0f} s"
    )


def figure(cases: dict) -> Path:
    """RSD curves of each group with results, one panel a group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [g for g, (_, members, _) in GROUPS.items()
              if any(_result(cases, f"{g}:{m}") for m in members)]  # fmt: skip
    if not groups:
        return RESULTS / f"{NAME}.png"
    cols = min(3, len(groups))
    rows = math.ceil(len(groups) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    for ax, group in zip(axes.flat, groups, strict=False):
        _, members, ref = GROUPS[group]
        for member in members:
            result = _result(cases, f"{group}:{member}")
            if result is None:
                continue
            cost = result["flow_wall_s"] + result["mix_wall_s"]
            width = 2 if member == ref else 1
            ax.semilogy(result["revolution"], result["rsd"], lw=width,
                        label=f"{member} ({cost:.0f} s)")  # fmt: skip
        ax.axhline(0.05, ls=":", color="tab:red", lw=1)
        ax.set_title(group, fontsize=9)
        ax.set_xlabel("revolutions")
        ax.set_ylabel("RSD")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(groups) :]:
        ax.axis("off")
    fig.tight_layout()
    from blendxr.plot import save_figure

    return save_figure(fig, RESULTS / f"{NAME}.png")


#: revolutions drawn; the last lies past where the coarser flows reach the floor, so the
#: run goes on without the scene's floor stop
DRUM_SNAPSHOTS = (0.5, 2.0, 4.0, 12.0)


def drum_figure() -> Path:
    """The drum's concentration at a few revolutions and its intensity curve, one row per
    member of ``drum_flow_cell_lw400`` (flows from the cache): where its answers part."""
    import matplotlib.pyplot as plt

    import blendxr as bx
    from blendxr import pipeline

    base, members, _ = GROUPS["drum_flow_cell_lw400"]
    n = len(DRUM_SNAPSHOTS)
    fig, axes = plt.subplots(len(members), n + 1, figsize=(3.2 * (n + 1), 2.8 * len(members)))
    for row, (member, values) in zip(axes, members.items(), strict=True):
        scene = bx.load_scene(
            base,
            {**values, "mixing.snapshots": list(DRUM_SNAPSHOTS),
             "mixing.revolutions": max(DRUM_SNAPSHOTS)},
        )  # fmt: skip
        flow, _ = pipeline.scene_flow(scene, cache=flow_cache(), progress=False)
        mixed = bx.mix(flow, scene, stop_intensity=None, progress=False)
        bed = mixed["c"].notnull().any("snapshot")  # the frame: where material ever is
        xs, ys = mixed.x.where(bed.any("y"), drop=True), mixed.y.where(bed.any("x"), drop=True)
        for ax, c in zip(row, mixed["c"], strict=False):
            ax.pcolormesh(mixed.x, mixed.y, c.T, vmin=0, vmax=1, cmap="coolwarm")
            ax.set_aspect("equal")
            ax.set_xlim(float(xs.min()), float(xs.max()))
            ax.set_ylim(float(ys.min()), float(ys.max()))
            ax.set_title(f"flow {member}, rev {float(c.snapshot_revolution):g}", fontsize=8)
            ax.tick_params(labelsize=6)
        ax = row[-1]
        ax.semilogy(mixed["revolution"], mixed["intensity"], label="intensity")
        ax.axhline(mixed.attrs["random_mixture_intensity"], ls=":", color="k", label="floor")
        ax.set_xlabel("revolutions", fontsize=8)
        ax.legend(fontsize=7)
    fig.suptitle("drum-calibration, Lax-Wendroff on 400 ADE cells, k1 = 0.01", fontsize=10)
    fig.tight_layout()
    from blendxr.plot import save_figure

    return save_figure(fig, RESULTS / f"{NAME}_drum.png")


#: k1 the "measured" curves are made at, their relative noise, the seeds, the fit's grid
CALIBRATION_TRUTH = 0.01
CALIBRATION_NOISE = (0.03, 0.1)
CALIBRATION_SEEDS = (1, 2)
CALIBRATION_GRID = (0.0, 0.005, 0.01, 0.02, 0.04)


def drum_calibration() -> dict:
    """How well `calibrate_k1` pins k1 down on the shipped drum: curves made by the model at
    k1 = CALIBRATION_TRUTH with multiplicative noise, every half revolution, fitted on
    CALIBRATION_GRID. Writes ``answer_precision_drum_calibration.json``."""
    from _common import machine, write_json

    import blendxr as bx
    from blendxr import pipeline

    scene = bx.load_scene("drum-calibration")
    flow, _ = pipeline.scene_flow(scene, cache=flow_cache(), progress=False)
    truth = bx.mix(flow, scene, k1=CALIBRATION_TRUTH, progress=False)
    curve = truth["intensity"].swap_dims(time="revolution").dropna("revolution")
    rows = []
    for noise in CALIBRATION_NOISE:
        for seed in CALIBRATION_SEEDS:
            rng = np.random.default_rng(seed)
            measured = curve * (1 + noise * rng.standard_normal(curve.size))
            measured = measured.isel(revolution=slice(1, None, 2)).rename("intensity")
            started = time.perf_counter()
            fit = bx.calibrate_k1(measured, scene, flow=flow, k1=list(CALIBRATION_GRID))
            rows.append(
                {
                    "noise": noise,
                    "seed": seed,
                    "best_k1": float(fit.attrs["best_k1"]),
                    "best_cost": float(fit.attrs["best_cost"]),
                    "source": fit.attrs["best_cost_source"],
                    "wall_s": time.perf_counter() - started,
                }
            )
            echo(f"noise {noise:.0%} seed {seed}: best k1 {rows[-1]['best_k1']:.4f} "
                 f"({rows[-1]['source']}), {rows[-1]['wall_s']:.0f} s")  # fmt: skip
    payload = {
        "machine": machine(),
        "scene": "drum-calibration (as shipped)",
        "truth_k1": CALIBRATION_TRUTH,
        "grid": CALIBRATION_GRID,
        "fits": rows,
    }
    write_json(f"{NAME}_drum_calibration", payload)
    echo(table(["noise", "seed", "best k1", "cost", "from", "wall s"],
               [[f"{r['noise']:.0%}", r["seed"], f"{r['best_k1']:.4f}", f"{r['best_cost']:.3f}",
                 r["source"], f"{r['wall_s']:.0f}"] for r in rows]))  # fmt: skip
    return payload


if __name__ == "__main__":
    if "--drum-calibration" in sys.argv:
        drum_calibration()
        raise SystemExit(0)
    if "--drum-figure" in sys.argv:
        echo(f"wrote {drum_figure()}")
        raise SystemExit(0)
    payload = run_cases(NAME, __doc__.splitlines()[0], CASES, run_case, report, summary)
    figure(payload["cases"])
