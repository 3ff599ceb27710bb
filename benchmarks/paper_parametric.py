"""The paper's parametric study (§6, Figs. 13-14) as one sweep.

60 % fill, side-side loading (``tote-60-side-side``), one parameter varied at a time
about the paper's values (k1 = 0.01, k2 = 1.9 k1, wall friction 0.324, internal friction
angle 27.1 deg):

- Fig. 13a, ``mixing.k1``: 0, 0.005, 0.01, 0.02;
- Fig. 13b, ``mixing.k2``: 0, 0.019 (the default 1.9 k1), 0.04;
- Fig. 14a, ``material.wall_friction``: 0.2, 0.324, 0.5;
- Fig. 14b, ``material.friction_angle_deg``: 22, 27.1, 32.

The k1 and k2 cases share one flow; each wall friction and friction angle needs its own
(five flows in all). ``--size small`` (default) runs the flows at a 20 mm cell with E/100 and
12 phase bins, mixed on 60 ADE cells for 30 revolutions (about 15 minutes on 2 cores);
``--size medium`` runs the shipped scene with a 10 mm flow cell (E/10, 36 bins, 100^3
ADE cells: five flows of about 5-10 minutes each, then the mixing); ``--size paper``
runs the shipped scene as it is (7.5 mm: five flows of about 25 minutes each, then the
mixing). Cases run through ``bx.sweep`` on a LocalCluster of
two one-thread workers, with their store in ``runs/paper_parametric-<size>/cases`` (a killed
run resumes there).

Writes ``benchmarks/results/paper_parametric_<size>.{nc,json,md,png}``: the RSD curves of
each panel, the revolutions to RSD 0.2 / 0.1 / 0.05 and the final RSD of every case.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "2")

import argparse  # noqa: E402
import math  # noqa: E402

from _common import (  # noqa: E402
    REPO,
    RESULTS,
    echo,
    flow_cache,
    machine,
    machine_line,
    sweep_report,
    write_atomic,
    write_json,
)

import blendxr as bx  # noqa: E402

BASE = "tote-60-side-side"
SIZES = {
    "small": {
        "flow.cell": 0.02,
        "solver.stiffness_scaling": 100.0,
        "flow.phases": 12,
        "numerics.cells": 60,
        "mixing.revolutions": 30,
    },
    "medium": {"flow.cell": 0.01},
    "paper": {},
}
PANELS = {
    "13a": ("mixing.k1", [0.0, 0.005, 0.01, 0.02]),
    "13b": ("mixing.k2", [0.0, 0.019, 0.04]),
    "14a": ("material.wall_friction", [0.2, 0.324, 0.5]),
    "14b": ("material.friction_angle_deg", [22.0, 27.1, 32.0]),
}
#: the paper's values of the varied keys (a case sets only the key of its panel)
PAPER = {"mixing.k1": 0.01, "mixing.k2": 0.019, "material.wall_friction": 0.324,
         "material.friction_angle_deg": 27.1}  # fmt: skip


def cases() -> list[dict]:
    """One case per panel value; the paper's values appear once (shared by the panels)."""
    out = [{}]
    for key, values in PANELS.values():
        out += [{key: v} for v in values if not math.isclose(v, PAPER[key])]
    return out


def panel_cases(key: str, values: list) -> list[dict]:
    return [{} if math.isclose(v, PAPER[key]) else {key: v} for v in values]


def rsd_after(result, case: dict, revolutions: float) -> float:
    """The RSD of ``case`` after ``revolutions`` (NaN past the case's end)."""
    from blendxr.sweep import case_id

    row = result.isel(case=list(result["case"].values).index(case_id(case)))
    rsd = row["rsd"].dropna("revolution")
    if rsd.size == 0 or float(rsd["revolution"].max()) < revolutions - 1e-9:
        return math.nan
    return float(rsd.interp(revolution=revolutions))


def common_end(result) -> float:
    """The last revolution every case reached (a case may stop early at its RSD target)."""
    ends = [float(result["rsd"].isel(case=i).dropna("revolution")["revolution"].max())
            for i in range(result.sizes["case"])]  # fmt: skip
    return min(ends)


def trends(result) -> str:
    """The paper's statements on Figs. 13-14 (§6) against this sweep, with the figures:
    the RSD of each panel's cases after the last revolution they all reached."""
    n = common_end(result)
    at = {panel: [rsd_after(result, c, n) for c in panel_cases(key, values)]
          for panel, (key, values) in PANELS.items()}  # fmt: skip
    base = rsd_after(result, {}, n)

    def listing(panel):
        key, values = PANELS[panel]
        name = key.split(".")[-1]
        pairs = ", ".join(f"{v:g}: {r:.3f}" for v, r in zip(values, at[panel], strict=True))
        return f"{name} = {pairs}"

    def spread(panel):
        return (max(at[panel]) - min(at[panel])) / base

    k1_falls = all(b < a for a, b in zip(at["13a"], at["13a"][1:], strict=False))
    k2_zero = at["13b"][PANELS["13b"][1].index(0.0)]
    k1_zero = at["13a"][PANELS["13a"][1].index(0.0)]
    # k1 = 0 removes all diffusion (k2 follows k1 as 1.9 k1 unless set); k2 = 0 keeps
    # the k1 term alone: the k1 term's share is k1_zero - k2_zero, the k2 term's the rest
    k1_term, k2_term = k1_zero - k2_zero, k2_zero - base
    lines = [
        f"## The paper's statements (§6) against this sweep (RSD after {n:g} revolutions)",
        "",
        f"- *A larger k1 mixes faster* (Fig. 13a): {listing('13a')}: "
        f"{'holds' if k1_falls else 'does not hold'}; diffusion (k1 = 0.01, k2 = 1.9 k1) "
        f"lowers the purely advective RSD by {1 - base / k1_zero:.0%}.",
        f"- *The k1 term matters more than the k2 term* (Fig. 13): {listing('13b')}. The k1 "
        f"term alone (k2 = 0) lowers the advective RSD by {k1_term:.3f}, the k2 term then "
        f"by {k2_term:.3f}: {'holds' if k1_term > k2_term else 'does not hold'}.",
        f"- *Wall friction barely matters* (Fig. 14a): {listing('14a')}: the RSD spans "
        f"{spread('14a'):.0%} of the paper's value over the panel.",
        f"- *Internal friction plays little role* (Fig. 14b, §7): {listing('14b')}: the "
        f"RSD spans {spread('14b'):.0%} of the paper's value over the panel.",
        "",
    ]
    return "\n".join(lines)


def figure(result, size: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blendxr.plot import save_figure
    from blendxr.sweep import case_id

    fig, axes = plt.subplots(2, 2, figsize=(10, 7), sharey=True)
    ids = list(result["case"].values)
    for ax, (panel, (key, values)) in zip(axes.flat, PANELS.items(), strict=True):
        for value, case in zip(values, panel_cases(key, values), strict=True):
            row = result.isel(case=ids.index(case_id(case)))
            ax.semilogy(result["revolution"], row["rsd"], label=f"{key.split('.')[-1]} = {value:g}")
        ax.set_title(f"Fig. {panel}: {key}", fontsize=10)
        ax.set_xlabel("revolutions")
        ax.set_ylabel("RSD")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"60 % fill, side-side loading ({size} size)")
    fig.tight_layout()
    return save_figure(fig, RESULTS / f"paper_parametric_{size}.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", choices=list(SIZES), default="small")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    info = machine()
    echo(f"machine: {machine_line(info)}")
    base = bx.load_scene(BASE, SIZES[args.size])
    store = REPO / "runs" / f"paper_parametric-{args.size}" / "cases"
    result = bx.sweep(base, cases(), store=store, cache=flow_cache(), workers=args.workers)
    from blendxr.io import write_result
    from blendxr.sweep import case_id

    write_result(result, RESULTS / f"paper_parametric_{args.size}.nc", scene=base,
                 title="the paper's parametric study (Figs. 13-14)")  # fmt: skip
    ids = list(result["case"].values)
    rows, payload = [], []
    for panel, (key, values) in PANELS.items():
        for value, case in zip(values, panel_cases(key, values), strict=True):
            row = result.isel(case=ids.index(case_id(case)))
            to = [float(v) for v in row["revolutions_to_rsd"].values]
            rows.append([panel, key, value, *("-" if math.isnan(v) else f"{v:.1f}" for v in to),
                         f"{float(row['final_rsd']):.3f}", str(row["status"].values)])  # fmt: skip
            payload.append({"panel": panel, "key": key, "value": value, "to_rsd": to,
                            "final_rsd": float(row["final_rsd"]),
                            "status": str(row["status"].values)})  # fmt: skip
    text = sweep_report(
        f"The paper's parametric study (Figs. 13-14), {args.size} size", info, result,
        ["fig.", "key", "value", "N(0.2)", "N(0.1)", "N(0.05)", "final RSD", "status"], rows,
    )  # fmt: skip
    text += "\n" + trends(result)
    write_json(f"paper_parametric_{args.size}", {"machine": info, "sweep": dict(result.attrs),
                                                 "cases": payload})  # fmt: skip
    write_atomic(RESULTS / f"paper_parametric_{args.size}.md", text)
    figure(result, args.size)
    echo(text)


if __name__ == "__main__":
    main()
