"""The paper's studies end to end: the four Tote cases of section 6 and the calibration drum.

Each case runs as ``blendxr run NAME`` does (``bx.run_scene``: flow from the cache or
solved, mixing, report) into ``runs/paper/NAME/`` of the checkout; this script then
gathers the answers into ``benchmarks/results/paper_cases.{json,md}`` and draws
``paper_cases_tote.png`` (the four Tote RSD curves on one plot with their random-mixture
floors, like the paper's Fig. 12) and ``paper_cases_drum.png`` (the drum's segregation
intensity with its floor, like Fig. 7). The committed per-case ``report.json`` and
pictures are copied beside them under ``results/paper/NAME/``.

``--sweep SIZE`` runs the four Tote cases instead as one ``bx.sweep`` (fill x loading
about ``tote-40-top-bottom``, a LocalCluster of two one-thread workers, its store in
``runs/paper_cases_sweep-SIZE/``): ``small`` at a 20 mm flow cell, E/100, 12 phase bins,
60 ADE cells (minutes), ``paper`` at the scenes' own resolution (the flows of the runs
above, from the cache). It writes ``paper_cases_sweep_SIZE.{md,png}`` (the four RSD
curves with their random-mixture floors, like Fig. 12).

Run: ``python benchmarks/paper_cases.py [--case NAME ...] [--reuse DIR]``. ``--reuse DIR``
reads finished runs from ``DIR/NAME/`` (``mixing.nc`` and ``report.json`` written by
``blendxr run NAME -o DIR/NAME``) instead of running them again. A Tote case at the
paper's resolution takes tens of minutes for its flow (shared by the two loadings of one
fill) and minutes of mixing: ``results/paper_cases.md`` gives the measured times.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "2")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

from _common import (  # noqa: E402
    REPO,
    RESULTS,
    echo,
    flow_cache,
    machine,
    machine_line,
    merge_cases,
    portable,
    sweep_report,
    table,
    write_atomic,
)

NAME = "paper_cases"
TOTE = ("tote-40-top-bottom", "tote-40-side-side", "tote-60-top-bottom", "tote-60-side-side")
DRUM = "drum-calibration"
CASES = (*TOTE, DRUM)
PICTURES = ("mixing.png", "snapshots.png", "report.json")


def _run(case: str, folder: Path) -> Path:
    import blendxr as bx

    out = folder / case
    bx.run_scene(case, out, cache=flow_cache(), progress=False)
    return out


def _collect(case: str, out: Path) -> dict:
    import blendxr as bx

    report = json.loads((out / "report.json").read_text())
    mixed = bx.open_mixing(out / "mixing.nc")
    keep = RESULTS / "paper" / case
    keep.mkdir(parents=True, exist_ok=True)
    for name in PICTURES:
        if (out / name).exists():
            shutil.copyfile(out / name, keep / name)
    if (keep / "report.json").exists():  # the committed copy names no machine's paths
        write_atomic(keep / "report.json", portable((keep / "report.json").read_text()))
    return {
        "report": report,
        "revolution": mixed["revolution"].values.tolist(),
        "rsd": mixed["rsd"].values.tolist(),
        "intensity": [None if v != v else v for v in mixed["intensity"].values.tolist()],
    }


def _fmt(value, spec=".2f", missing="not reached"):
    return missing if value is None else format(value, spec)


def report_md(cases: dict, info: dict) -> str:
    rows = []
    for case in (c for c in CASES if c in cases):
        result = cases[case]
        r = result["report"]
        m, f, stages = r["mixing"], r["flow"], r["stages"]
        n = m["revolutions_to_rsd"]
        p = f.get("periodicity_eq30", {})
        rows.append(
            [
                case,
                _fmt(n.get("0.1")),
                _fmt(n.get("0.05")),
                f"{m['final_rsd']:.4f}",
                _fmt(m["final_intensity"], ".4f", "n/a"),
                _fmt(m["random_mixture_rsd"], ".4f", "n/a"),
                _fmt(m["random_mixture_intensity"], ".4f", "n/a"),
                " / ".join(f"{v:.0%}" for v in p.values()),
                _fmt(f.get("fill_share"), ".1%", "n/a"),
                f"{f.get('wall_time_s', float('nan')):.0f}",
                f"{stages['mixing']['wall_s']:.0f}",
                f"{stages['mixing']['peak_memory_mb']:.0f}",
            ]
        )
    return "\n".join(
        [
            "# The paper's studies end to end",
            "",
            f"Machine: {machine_line(info)}. `benchmarks/paper_cases.py`; each row is "
            "`blendxr run NAME` (report and pictures in `results/paper/NAME/`).",
            "",
            table(
                [
                    "case",
                    "N(0.1)",
                    "N(0.05)",
                    "final RSD",
                    "final I",
                    "RSD_R",
                    "I_R",
                    "eq. 30 x/y/z",
                    "fill",
                    "flow s",
                    "mix s",
                    "mix MiB",
                ],  # fmt: skip
                rows,
            ),
            "",
            "N(x): revolutions to RSD x. RSD_R, I_R: the random-mixture floors on the "
            "sampling cells (five bead diameters). Flow s: the solve's wall time (the "
            "two loadings of one fill share one flow).",
            "",
        ]
    )


def figures(cases: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blendxr.plot import save_figure

    tote = [c for c in TOTE if c in cases]
    if tote:
        fig, ax = plt.subplots(figsize=(6.5, 4.2))
        for case in tote:
            result = cases[case]
            (line,) = ax.plot(result["revolution"], result["rsd"], lw=1.5, label=case)
            floor = result["report"]["mixing"]["random_mixture_rsd"]
            if floor is not None:
                ax.axhline(floor, ls="--", lw=0.8, color=line.get_color())
        ax.axhline(0.05, ls=":", color="k", lw=1, label="RSD 5 %")
        ax.set_xlabel("revolutions")
        ax.set_ylabel("RSD")
        ax.set_title("Tote, 10 rpm, k1 = 0.01 (dashed: random mixture of each case)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        save_figure(fig, RESULTS / f"{NAME}_tote.png")
    if DRUM in cases:
        result = cases[DRUM]
        fig, ax = plt.subplots(figsize=(6, 4))
        values = [float("nan") if v is None else v for v in result["intensity"]]
        ax.semilogy(result["revolution"], values, lw=1.5, label="model, k1 = 0.01")
        floor = result["report"]["mixing"]["random_mixture_intensity"]
        if floor is not None:
            ax.axhline(floor, ls="--", color="k", lw=1, label=f"random mixture {floor:.3f}")
        ax.set_xlabel("revolutions")
        ax.set_ylabel("segregation intensity")
        ax.set_title("calibration drum (Table 2)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        save_figure(fig, RESULTS / f"{NAME}_drum.png")


#: the four Tote cases as one sweep about tote-40-top-bottom
SWEEP = {"fill.fraction": [0.4, 0.6], "mixing.loading": ["top-bottom", "side-side"]}
SWEEP_SIZES = {
    "small": {
        "flow.cell": 0.02,
        "solver.stiffness_scaling": 100.0,
        "flow.phases": 12,
        "numerics.cells": 60,
        "mixing.revolutions": 40,
    },
    "paper": {},
}


def tote_sweep(size: str, info: dict) -> None:
    """The four Tote cases as one bx.sweep; table and Fig. 12-like plot."""
    import math

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import xarray as xr

    import blendxr as bx
    from blendxr.plot import save_figure
    from blendxr.sweep import case_id

    base = bx.load_scene("tote-40-top-bottom", SWEEP_SIZES[size])
    store = REPO / "runs" / f"paper_cases_sweep-{size}"
    result = bx.sweep(base, SWEEP, store=store, cache=flow_cache(), workers=2)
    rows = []
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for fill in SWEEP["fill.fraction"]:
        for loading in SWEEP["mixing.loading"]:
            case = result.sel({"fill.fraction": fill, "mixing.loading": loading})
            label = f"{fill:.0%} {loading}"
            (line,) = ax.semilogy(result["revolution"], case["rsd"], lw=1.5, label=label)
            one = store / f"case-{case_id({'fill.fraction': fill, 'mixing.loading': loading})}.nc"
            with xr.open_dataset(one) as ds:
                floor = float(ds.attrs.get("random_mixture_rsd", math.nan))
            if math.isfinite(floor):
                ax.axhline(floor, ls="--", lw=0.8, color=line.get_color())
            to = [float(v) for v in case["revolutions_to_rsd"].values]
            rows.append([label, *("not reached" if math.isnan(v) else f"{v:.1f}" for v in to),
                         f"{float(case['final_rsd']):.3f}", f"{float(case['mix_wall_time']):.0f}",
                         str(case["status"].values)])  # fmt: skip
    ax.axhline(0.05, ls=":", color="k", lw=1, label="RSD 5 %")
    ax.set_xlabel("revolutions")
    ax.set_ylabel("RSD")
    ax.set_title(f"Tote, 10 rpm, k1 = 0.01, one sweep ({size}; dashed: random mixture)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, RESULTS / f"{NAME}_sweep_{size}.png")
    text = sweep_report(
        f"The four Tote cases as one sweep ({size} size)", info, result,
        ["case", "N(0.2)", "N(0.1)", "N(0.05)", "final RSD", "mixing s", "status"], rows,
    )  # fmt: skip
    write_atomic(RESULTS / f"{NAME}_sweep_{size}.md", text)
    echo(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", action="append", choices=CASES)
    parser.add_argument("--reuse", type=Path, help="read finished runs from DIR/NAME/")
    parser.add_argument("--sweep", choices=list(SWEEP_SIZES),
                        help="run the four Tote cases as one bx.sweep at this size")  # fmt: skip
    args = parser.parse_args()
    info = machine()
    echo(f"machine: {machine_line(info)}")
    if args.sweep:
        tote_sweep(args.sweep, info)
        return
    for case in args.case or CASES:
        out = args.reuse / case if args.reuse else _run(case, REPO / "runs" / "paper")
        result = _collect(case, out)
        echo(f"{case}: {result['report']['mixing']['revolutions_to_rsd']}")
        payload = merge_cases(NAME, {"machine": info, "cases": {case: result}}, report_md)
    figures(payload["cases"])
    echo(report_md(payload["cases"], info))


if __name__ == "__main__":
    main()
