"""Issue 35, items 9 and 13: `xyzcyl client render` answers a flag it does not know with its own usage (not
`xyzcyl client [-h] ACTION`) and takes --format (which must agree with --out's extension); `xyzcyl --version` names
the default model's version too; `xyzcyl render --quiet` prints nothing but errors. Also the move fields' one
definition (common.poses.CameraMove) as every front end declares it. No server: the client's requests are captured
with httpx.MockTransport."""

from __future__ import annotations

import json
from importlib.metadata import version

import numpy as np
import pytest
from client_helpers import PNG
from xyzcyl import cli

httpx = pytest.importorskip("httpx")



def _client(capsys, *args) -> tuple[int, str]:
    capsys.readouterr()
    try:
        rc = cli.main(["client", "render", "SID", "--server", "http://test", "--quiet", *args])
    except SystemExit as e:          # argparse's usage errors
        rc = e.code
    return rc, capsys.readouterr().err


# -- a flag the action does not know -----------------------------------------------------------------------------

@pytest.mark.parametrize("flag", [["--bogus"], ["--fromat", "jpeg"], ["--widht", "80"]])
def test_an_unknown_flag_prints_the_actions_usage(sent, tmp_path, capsys, flag):
    rc, err = _client(capsys, "--camera", "CAM_FRONT", "--out", str(tmp_path / "v.png"), *flag)
    assert rc == 2 and not sent
    assert err.startswith("usage: xyzcyl client render "), err
    assert "xyzcyl client [-h] ACTION" not in err
    assert f"xyzcyl client render: error: unrecognized arguments: {' '.join(flag)}" in err, err


def test_an_unknown_flag_of_another_action_prints_that_actions_usage(capsys):
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        cli.main(["client", "scenes", "--server", "http://test", "--bogus"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("usage: xyzcyl client scenes "), err


# -- --format ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("out, fmt", [("v.png", "png"), ("v.jpg", "jpeg"), ("v.JPEG", "jpeg"), ("v.exr", "exr"),
                                      ("view", "jpeg"), ("view", "exr")])
def test_format_agrees_with_out(sent, tmp_path, capsys, out, fmt):
    rc, err = _client(capsys, "--camera", "CAM_FRONT", "--out", str(tmp_path / out), "--format", fmt)
    assert rc == 0, err
    assert sent[-1]["format"] == fmt and (tmp_path / out).read_bytes() == PNG


@pytest.mark.parametrize("out, fmt, field", [("v.png", "jpeg", "--format"), ("v.jpg", "png", "--format"),
                                             ("v.exr", "png", "--format"), ("v.gif", "png", "--out"),
                                             ("v.gif", None, "--out"), ("view", None, "--out")])
def test_format_disagreeing_with_out_is_refused(sent, tmp_path, capsys, out, fmt, field):
    rc, err = _client(capsys, "--camera", "CAM_FRONT", "--out", str(tmp_path / out),
                      *(["--format", fmt] if fmt else []))
    assert rc == 2 and not sent
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"xyzcyl client: {field}: "), err


def test_without_format_the_extension_decides(sent, tmp_path, capsys):
    for out, fmt in (("a.png", "png"), ("a.jpeg", "jpeg"), ("a.exr", "exr")):
        rc, err = _client(capsys, "--camera", "CAM_FRONT", "--out", str(tmp_path / out))
        assert rc == 0 and sent[-1]["format"] == fmt, err


# -- moves and a lens on an input camera, sent to the server ---------------------------------------------------

def test_client_render_sends_the_move_and_lens_of_an_input_camera(sent, tmp_path, capsys):
    lens = {"model": "opencv_fisheye", "k1": 0.02, "max_angle_deg": 95}
    rc, err = _client(capsys, "--camera", "CAM_FRONT", "--forward", "1", "--yaw", "-1.5e1", "--distortion",
                      json.dumps(lens), "--out", str(tmp_path / "v.png"))
    assert rc == 0, err
    p = sent[-1]
    assert p["camera"] == "CAM_FRONT" and json.loads(p["distortion"]) == lens
    assert (float(p["forward"]), float(p["yaw"])) == (1.0, -15.0) and "left" not in p and "up" not in p


def test_view_params_take_the_move_alike():
    """Client.view_params: a move= argument and the move's keys in an input-camera or OpenCV dict give the same
    query; on a CARLA pose the move is folded into the transform; bad values name the field."""
    from xyzcyl.clients.client import InvalidRequestError, view_params
    from xyzcyl.common.poses import CameraMove

    move = {"forward": 2, "left": -1, "yaw": 30}
    a = view_params("CAM_FRONT", move=move)
    assert a == view_params({"camera": "CAM_FRONT", **move}) == view_params("CAM_FRONT", move=CameraMove(**move))
    assert a == {"camera": "CAM_FRONT", "forward": "2.0", "left": "-1.0", "yaw": "30.0"}
    pose = np.eye(4).ravel().tolist()
    b = view_params({"cam_to_ego": pose, "fov": 90, **move}, 64, 48)      # the server moves the pose
    assert [float(v) for v in b["cam_to_ego"].split(",")] == pose and (b["forward"], b["yaw"]) == ("2.0", "30.0")
    carla = view_params({"x": 1, "y": 0, "z": 1.5, "pitch": 0, "yaw": 0, "roll": 0, "fov": 90}, 64, 48, move=move)
    assert "forward" not in carla and (carla["x"], carla["y"], carla["yaw"]) == ("3.0", "1.0", "-30.0")
    for bad, field in (({"forward": float("nan")}, "move.forward"), ({"fwd": 1}, "move.fwd"),
                       ({"yaw": 400}, "move.yaw")):
        with pytest.raises(InvalidRequestError) as e:
            view_params("CAM_FRONT", move=bad)
        assert e.value.field == field, e.value
    with pytest.raises(InvalidRequestError) as e:
        view_params({"camera": "CAM_FRONT", "forward": 1}, move={"left": 1})
    assert e.value.field == "move"


def test_move_fields_are_defined_once():
    """CameraMove's fields are the flags of both render commands, the GET query's parameters and the batch items'
    keys, with their units and bounds."""
    import argparse

    from xyzcyl.common.poses import MOVE_FIELDS, MOVE_NAMES, CameraMove, MoveError, add_move_arguments
    from xyzcyl.common.wire import _OPENCV_FOV_KEYS, _OPENCV_K_KEYS, _RIG_KEYS

    assert MOVE_NAMES == ("forward", "left", "up", "yaw")
    assert [(f.unit, f.limit) for f in MOVE_FIELDS] == [("metres", 1000.0)] * 3 + [("degrees", 360.0)]
    p = argparse.ArgumentParser()
    add_move_arguments(p)
    assert {a.dest for a in p._actions} >= set(MOVE_NAMES)
    for keys in (_RIG_KEYS, _OPENCV_K_KEYS, _OPENCV_FOV_KEYS):
        assert set(MOVE_NAMES) <= set(keys)
    assert CameraMove(1, 2, 3, 4) == CameraMove.from_values({"forward": 1, "left": 2.0, "up": 3, "yaw": 4})
    for bad, field in (({"forward": True}, "forward"), ({"up": "1"}, "up"), ({"left": 1001}, "left"),
                       ({"yaw": -361}, "yaw"), ({"forward": float("inf")}, "forward")):
        with pytest.raises(MoveError) as e:
            CameraMove.from_values(bad)
        assert e.value.field == field


# -- --version ---------------------------------------------------------------------------------------------------

def test_version_names_the_default_model(capsys, monkeypatch):
    from xyzcyl.testing import SHIPPED_MODEL

    meta = json.loads((SHIPPED_MODEL / "model.json").read_text())
    monkeypatch.setenv("XYZCYL_MODEL", str(SHIPPED_MODEL))
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    out = capsys.readouterr().out.splitlines()
    assert e.value.code == 0
    assert out[0] == f"xyzcyl {version('xyzcyl')}"
    assert out[1].startswith(f"model: {meta['name']} {meta['version']} ("), out


def test_version_without_a_model(capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("XYZCYL_MODEL", str(tmp_path / "nowhere"))
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.splitlines()[1].startswith("model: not found")


def test_version_imports_no_torch():
    """--version reads model.json only (runtime.model_folder): no torch, and no numba or onnxruntime either."""
    import subprocess
    import sys

    code = ("import sys\nfrom xyzcyl import cli\ntry:\n    cli.main(['--version'])\nexcept SystemExit:\n"
            "    pass\nfor m in ('torch', 'numba', 'onnxruntime'):\n    assert m not in sys.modules, m + ' imported'\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[1].startswith("model: ")


# -- xyzcyl render --quiet ---------------------------------------------------------------------------------------

@pytest.fixture
def ply(tmp_path):
    from xyzcyl.runtime.render import Gaussians

    rng = np.random.default_rng(0)
    n = 50
    g = Gaussians(means=rng.uniform([2, -1, -1], [6, 1, 1], (n, 3)).astype(np.float32),
                  quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), log_scales=np.full((n, 3), -2.0, np.float32),
                  opacity_logits=np.full(n, 1.5, np.float32), sh=rng.normal(0, 0.5, (n, 1, 3)).astype(np.float32))
    path = tmp_path / "g.ply"
    g.save_ply(path)
    return path


def _render(ply, out, *extra):
    c2e = ["0", "0", "1", "0", "-1", "0", "0", "0", "0", "-1", "0", "0", "0", "0", "0", "1"]   # looking along ego x
    return cli.main(["render", str(ply), "--width", "32", "--height", "24", "--fov", "60", "--cam-to-world", *c2e,
                     "--out", str(out), *extra])


def test_render_quiet_prints_nothing(ply, tmp_path, capfd, monkeypatch):
    from xyzcyl.runtime import compile_notice

    sinks = []
    monkeypatch.setattr(compile_notice, "install", lambda sink=None: sinks.append(sink))
    capfd.readouterr()
    assert _render(ply, tmp_path / "a.png") == 0
    out, err = capfd.readouterr()
    assert out.startswith("rendered 50 Gaussians") and not sinks
    assert _render(ply, tmp_path / "b.png", "--quiet", "--forward", "0.5") == 0
    assert capfd.readouterr() == ("", "")
    assert len(sinks) == 1 and sinks[0]("xyzcyl: compiling numba kernels ...") is None     # the notice: nowhere
    assert (tmp_path / "b.png").read_bytes()[:8] == PNG[:8]
    # errors still say so
    assert _render(ply, tmp_path / "c.bmp", "--quiet") == 2
    out, err = capfd.readouterr()
    assert out == "" and err.startswith("xyzcyl render: --out: extension must be"), err


def test_render_format_flag(ply, tmp_path, capfd):
    assert _render(ply, tmp_path / "v", "--format", "jpeg", "-q") == 0
    assert (tmp_path / "v").read_bytes()[:3] == b"\xff\xd8\xff"
    capfd.readouterr()
    assert _render(ply, tmp_path / "v.png", "--format", "jpeg", "-q") == 2
    assert capfd.readouterr().err.startswith("xyzcyl render: --format: jpeg does not match --out's extension")
