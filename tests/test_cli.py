"""The blendxr command: main job, file outputs, and one-line errors with status 2."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import blendxr as bx
from blendxr.cli import main
from blendxr.pipeline import _blocks


def test_mix_writes_valid_files_and_a_picture(tmp_path, capsys):
    status = main(
        [
            "mix",
            "swirl-2d",
            "-o",
            str(tmp_path),
            "--revolutions",
            "0.5",
            "--cells",
            "24",
            "--save-flow",
            "-q",
        ]
    )
    assert status == 0
    for name in ("mixing.nc", "flow.nc", "mixing.png"):
        assert (tmp_path / name).stat().st_size > 0
    mixed = bx.open_mixing(tmp_path / "mixing.nc")
    bx.validate(mixed)
    assert bx.load_scene(mixed.attrs["scene"]).name == "swirl-2d"
    np.testing.assert_allclose(mixed["revolution"].values[-1], 0.5)
    out = capsys.readouterr().out
    assert "RSD" in out and "wall time" in out


@pytest.mark.parametrize(
    "argv, word",
    [
        (["mix", "no-such-scene"], "no-such-scene"),
        (["mix", "swirl-2d", "--k1", "-1"], "k1"),
        (["mix", "swirl-2d", "--dt", "1000", "--revolutions", "0.1"], "stability limit"),
        (["validate", "missing.nc"], "missing.nc"),
        (["validate", "."], "is a directory"),
        (["info", "."], "is a directory"),
        (["mix", "swirl-2d", "--cells", "100000"], "MiB"),
        (["mix", "swirl-2d", "--output-every", "1e-12"], "records"),
        (["mix", "swirl-2d", "--revolutions", "1e9"], "<= 100000"),
        (["mix", "swirl-2d", "--set", "flow.parameters.omegga=1"], "omegga"),
        (["flow", "drum-2d-mpm", "--set", "operation.rpm=nan"], "not a finite number"),
        (["flow", "drum-2d-mpm", "--set", "solver.stiffness_scaling=inf"], "finite"),
        (["flow", "drum-2d-mpm", "--set", "operation.rpm=1e6"], "critical speed"),
        (["flow", "drum-2d-mpm", "--cell", "1e-9"], "choose solver.cell >="),
        (["mix", "swirl-2d", "--dt", "1e-9", "--cells", "8"], "steps"),
    ],
)
def test_bad_input_gives_one_line_and_status_2(argv, word, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "-q"] if argv[0] == "mix" else argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and word in err and "Traceback" not in err


def test_validate_names_every_failing_file_and_goes_on(tmp_path, capsys):
    flow = bx.flows.uniform(velocity=(0.1, 0.0), cells=8)
    bx.write_dataset(flow, tmp_path / "good.nc")
    (tmp_path / "text.nc").write_text("not netCDF")
    files = [str(tmp_path / n) for n in ("text.nc", "good.nc", "gone.nc")]
    assert main(["validate", *files]) == 2
    captured = capsys.readouterr()
    assert "good.nc: valid flow/1" in captured.out
    err = captured.err.splitlines()
    assert "text.nc" in err[0] and "not a readable netCDF file" in err[0]
    assert "gone.nc" in err[1] and "no such file" in err[1]
    assert err[2] == "blendxr: 2 of 3 files not valid"


def test_debug_shows_the_traceback(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(bx.SceneError):
        main(["--debug", "mix", "swirl-2d", "--cells", "0", "-q"])


def test_an_internal_fault_is_one_line_with_status_3(monkeypatch, capsys):
    import blendxr.cli as cli

    def broken(args):
        raise TypeError("a bug")

    monkeypatch.setattr(cli, "_cmd_scenes", broken)
    assert main(["scenes"]) == 3
    err = capsys.readouterr().err.strip()
    assert err.startswith("blendxr: internal error: TypeError: a bug") and "--debug" in err


def test_invalid_dataset_is_reported_by_validate(tmp_path, capsys):
    flow = bx.flows.uniform(velocity=(0.1, 0.0), cells=8)
    flow["vx"].attrs["units"] = "km/h"
    flow.to_netcdf(tmp_path / "bad.nc")
    assert main(["validate", str(tmp_path / "bad.nc")]) == 2
    assert "vx" in capsys.readouterr().err


@pytest.mark.slow
def test_console_script_error_has_no_traceback(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "blendxr.cli", "mix", "nope"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2
    assert "Traceback" not in run.stderr and run.stderr.startswith("blendxr: error:")


def test_scenes_lists_builtin_scenes(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in bx.builtin_scenes():
        assert name in out


@pytest.mark.slow
def test_flow_verb_solves_writes_a_valid_flow_and_particles(tmp_path, capsys):
    status = main(["flow", "drum-2d-mpm", "-o", str(tmp_path), "--particles", "-q"])
    assert status == 0
    flow = bx.open_flow(tmp_path / "flow.nc")  # validates
    assert flow.attrs["frame"] == "lab"
    assert bx.load_scene(flow.attrs["scene"]).name == "drum-2d-mpm"
    assert (tmp_path / "particles.nc").stat().st_size > 0
    out = capsys.readouterr().out
    assert "particle updates/s" in out and "periodicity" in out
    turned = np.atleast_1d(flow.attrs["periodicity_history_revolution"])
    assert f"eq. 30 by revolution (x / y): {turned[0] - 1}-{turned[0]} " in out
    spacing = flow.attrs["occupied_volume_over_seeded"]
    assert f"{spacing:.3f} by the particles' spacing" in out


@pytest.mark.parametrize(
    ("last", "n", "label"),
    [(3, 1, "2-3"), (4, 2, "1-2 to 3-4"), (4, 3, "1 to 2-4"), (7, 3, "2-4 to 5-7")],
)
def test_periodicity_history_names_the_revolutions_compared(last, n, label):
    # with solver.average_revolutions = n each entry compares two blocks of n revolutions
    # (the first may be shorter), labelled in the flow by the later block's last
    assert _blocks(last, n) == label


@pytest.mark.slow
def test_flow_verb_refuses_a_scene_value_out_of_range(tmp_path, capsys):
    scene = tmp_path / "bad.toml"
    scene.write_text(
        'name = "bad"\n[vessel]\nkind = "drum"\nndim = 2\ndiameter = 0.15\n'
        "[fill]\nfraction = 0.4\n[material]\ndensity = -5.0\n"
    )
    assert main(["flow", str(scene), "-o", str(tmp_path), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "material.density" in err


@pytest.mark.slow
def test_run_without_a_scene_solves_the_default_tote_and_mixes(tmp_path, capsys):
    """The README's first command (mixing shortened): flow solver + mixing + report."""
    status = main(["run", "-o", str(tmp_path), "--revolutions", "1", "--cells", "30", "-q"])
    assert status == 0
    flow = bx.open_flow(tmp_path / "flow.nc")
    assert bx.load_scene(flow.attrs["scene"]).name == "tote-small"
    assert flow.attrs["frame"] == "vessel" and flow.sizes["rev_phase"] == 12
    bx.validate(bx.open_mixing(tmp_path / "mixing.nc"))
    assert (tmp_path / "mixing.png").stat().st_size > 0
    captured = capsys.readouterr()
    assert "RSD" in captured.out and "the flow's fill holds" in captured.out
    # with -q, standard error holds warnings only (their form: the test below)
    assert "Traceback" not in captured.err
    assert all(line.startswith("blendxr: warning: ") for line in captured.err.splitlines())


def test_a_warning_is_one_line_like_the_errors(monkeypatch, capsys):
    import warnings

    import blendxr.cli as cli

    def warns(args):
        warnings.warn("the flow's fill holds 90 % of the bed:\n  see docs/flow.md", stacklevel=2)
        return 0

    monkeypatch.setattr(cli, "_cmd_scenes", warns)
    assert main(["scenes"]) == 0
    err = capsys.readouterr().err
    assert err == "blendxr: warning: the flow's fill holds 90 % of the bed: see docs/flow.md\n"


def test_a_foreign_checkpoint_is_refused_and_no_resume_starts_afresh(tmp_path, capsys):
    base = ["mix", "swirl-2d", "--cells", "16", "--revolutions", "0.25", "-q", "-o",
            str(tmp_path), "--checkpoint", str(tmp_path / "run.ckpt")]  # fmt: skip
    assert main(base) == 0
    assert main([*base, "--k1", "0.2"]) == 2
    assert "--no-resume" in capsys.readouterr().err
    assert main([*base, "--k1", "0.2", "--no-resume"]) == 0
