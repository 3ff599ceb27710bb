"""The Tote blender through the flow solver at a coarse cell: the whole chain holds.

Coarse (25 mm cells, E / 100, 8 phase bins) so that the file runs in about a minute;
the periodicity at finer cells is measured by ``benchmarks/flow_tote.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import blendxr as bx
from blendxr.flow.solver import FlowSimulation


@pytest.mark.slow
@pytest.mark.parametrize("fraction", [0.4, 0.6])
def test_tote_flow_is_valid_stays_inside_and_mixes(fraction):
    scene = {
        "name": f"tote-{fraction:g}",
        "vessel": {"kind": "tote", "ndim": 3},
        "operation": {"rpm": 10.0},
        "fill": {"fraction": fraction},
        "flow": {"cell": 0.025, "phases": 8},
        "solver": {"stiffness_scaling": 100.0, "settle_time": 0.3, "revolutions": 2},
    }
    sim = FlowSimulation(scene)
    deepest_escape = [-math.inf]

    def outside_check(s):  # every step: no material outside the vessel, ever
        deepest_escape[0] = max(deepest_escape[0], float(s.vessel.sdf(s.particles.x).max()))

    sim.run(progress=False, callback=outside_check)
    assert deepest_escape[0] <= 0.0
    flow = bx.validate(sim.dataset(wall=0.0))
    assert flow.sizes["rev_phase"] == 8 and flow.attrs["frame"] == "vessel"
    # the bed occupies the fraction of the vessel it was filled to (within the lattice's
    # one-layer surface error, about 25 % of the volume at this coarse cell)
    bed = float(flow["fill"].mean("rev_phase").sum()) * 0.025**3
    assert bed == pytest.approx(fraction * sim.vessel.volume, rel=0.25)
    for key in ("periodicity_vx", "periodicity_vy", "periodicity_vz"):
        assert math.isfinite(flow.attrs[key])
    # the revolution before, for what the choice of revolution does downstream: its own
    # averages, the same comparison of the two
    before = bx.validate(sim.dataset("previous", wall=0.0))
    fill_p, vel_p, _ = sim.previous.fields()
    np.testing.assert_array_equal(before["vz"].values, vel_p[..., 2])
    np.testing.assert_array_equal(before["fill"].values, fill_p)
    assert not np.array_equal(before["vz"].values, flow["vz"].values)
    assert before.attrs["periodicity_vz"] == flow.attrs["periodicity_vz"]
    mixed = bx.mix(flow, revolutions=0.5, cells=20, output_every=0.25, progress=False)
    assert np.isfinite(mixed["rsd"]).all()
    assert mixed.attrs["mass_a_relative_drift"] < 1e-12


@pytest.mark.slow
def test_the_solvers_own_particles_binned_give_its_own_flow(monkeypatch, tmp_path):
    """``bx.flows.from_particles`` on the particles the solver deposited in its last
    revolution, given in the lab frame as another code would write them, reproduces the
    solver's flow (the lab-frame turn undone to round-off)."""
    from blendxr.flow import averaging

    scene = bx.load_scene(
        {
            "name": "tote-2d",
            "vessel": {"kind": "tote", "ndim": 2},
            "operation": {"rpm": 10.0},
            "fill": {"fraction": 0.4},
            "flow": {"cell": 0.02, "phases": 6},
            "solver": {"stiffness_scaling": 100.0, "settle_time": 0.2, "revolutions": 2},
        }
    )
    sim = FlowSimulation(scene)
    samples = []
    original = averaging.PhaseAverager.add

    def recording(self, k, x, v, vol):
        samples.append((self, sim.t, x.copy(), v.copy(), vol.copy()))
        return original(self, k, x, v, vol)

    monkeypatch.setattr(averaging.PhaseAverager, "add", recording)
    sim.run(progress=False)
    monkeypatch.undo()
    own = sim.dataset()
    omega = 2 * math.pi * 10.0 / 60.0
    # the samples of the last revolution (a sample at a revolution's end belongs to it)
    last = [math.ceil((t - 0.2) * omega / (2 * math.pi) - 1e-9) == 2 for _, t, *_ in samples]
    kept = [(t, x, v, vol) for (_, t, x, v, vol), keep in zip(samples, last, strict=True) if keep]
    times, positions, velocities, volumes = [], [], [], []
    for t, x, v, vol in kept:  # vessel frame -> lab frame
        theta = omega * (t - 0.2)
        c, s = math.cos(theta), math.sin(theta)
        r = np.array([[c, -s], [s, c]])
        spin = np.stack([-omega * x[:, 1], omega * x[:, 0]], axis=1)
        times.append(t)
        positions.append(x @ r.T)
        velocities.append((v + spin) @ r.T)
        volumes.append(vol)
    binned = bx.flows.from_particles(
        positions, velocities, times, scene, volumes=volumes, frame="lab", t0=0.2
    )
    bx.validate(binned)
    assert binned.attrs["samples_per_phase"] == own.attrs["samples_per_phase"]
    for name in ("fill", "vx", "vy"):
        np.testing.assert_allclose(binned[name].values, own[name].values, rtol=0, atol=1e-6)
    # the same from a CSV in long form, as a DEM code would export it
    import pandas as pd

    rows = [
        pd.DataFrame({"t": t, "x": x[:, 0], "y": x[:, 1], "vx": v[:, 0], "vy": v[:, 1],
                      "volume": vol})
        for t, x, v, vol in zip(times, positions, velocities, volumes, strict=True)
    ]  # fmt: skip
    pd.concat(rows).to_csv(tmp_path / "particles.csv", index=False)
    from_csv = bx.flows.from_particles(tmp_path / "particles.csv", scene=scene, t0=0.2)
    np.testing.assert_allclose(from_csv["fill"].values, own["fill"].values, atol=1e-6)
