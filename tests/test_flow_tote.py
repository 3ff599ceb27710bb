"""The Tote blender through the flow solver at a coarse cell: the whole chain holds.

Coarse (25 mm cells, E / 100, 8 phase bins) so that the file runs in about a minute;
the periodicity at finer cells is measured by ``benchmarks/flow_tote.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import blendxr as bx
from blendxr.flow.solver import FlowSimulation, _flow_from


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
    flow = bx.validate(_flow_from(sim, 0.0, "time"))
    assert flow.sizes["rev_phase"] == 8 and flow.attrs["frame"] == "vessel"
    # the bed occupies the fraction of the vessel it was filled to (within the lattice's
    # one-layer surface error, about 25 % of the volume at this coarse cell)
    bed = float(flow["fill"].mean("rev_phase").sum()) * 0.025**3
    assert bed == pytest.approx(fraction * sim.vessel.volume, rel=0.25)
    for key in ("periodicity_vx", "periodicity_vy", "periodicity_vz"):
        assert math.isfinite(flow.attrs[key])
    # the revolution before, for what the choice of revolution does downstream: its own
    # averages, the same comparison of the two
    before = bx.validate(_flow_from(sim, 0.0, "time", revolution="previous"))
    fill_p, vel_p, _ = sim.previous.fields()
    np.testing.assert_array_equal(before["vz"].values, vel_p[..., 2])
    np.testing.assert_array_equal(before["fill"].values, fill_p)
    assert not np.array_equal(before["vz"].values, flow["vz"].values)
    assert before.attrs["periodicity_vz"] == flow.attrs["periodicity_vz"]
    mixed = bx.mix(flow, revolutions=0.5, cells=20, output_every=0.25, progress=False)
    assert np.isfinite(mixed["rsd"]).all()
    assert mixed.attrs["mass_a_relative_drift"] < 1e-12
