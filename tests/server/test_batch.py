"""`xyzcyl batch` (server/batch.py): the manifest's checks, the scene key and id, the store handles (folder and
S3 on moto), the failure rows; then the whole command on a local Ray over three drives, one broken, killed mid-way
and run again (tests at the end)."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_s3_store import bucket, s3_endpoint  # noqa: F401 - the moto fixtures (tests/server is on sys.path)
from xyzcyl.common.errors import FieldError
from xyzcyl.server import batch as B
from xyzcyl.server.store.folder import FolderStore
from xyzcyl.server.store.record import valid_id
from xyzcyl.testing.drives import cut_drive, pose, write_drive

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE_RIG = ROOT / "examples" / "synth_nuscenes" / "rig.json"
MODEL = {"name": "xyzcyl-cpu-v1", "version": "1.4.0", "model_json_sha256": "ab" * 32}


def _manifest(tmp_path: Path, text: str) -> str:
    p = tmp_path / "drives.txt"
    p.write_text(text)
    return str(p)


# ---------------------------------------------------------------------------------------------- the manifest

def test_manifest_lines_json_lines_and_relative_paths(tmp_path):
    write_drive(tmp_path / "a", [pose(0), pose(2)], [0.0, 0.5])
    m = _manifest(tmp_path, f"# drives\n\na/drive.json\n{{\"input\": \"{EXAMPLE_RIG}\", \"name\": \"ex\", "
                            "\"detail_stride\": null, \"keyframe_gap\": 1.5}\n")
    items = B.read_manifest(m)
    assert [i.input for i in items] == [str((tmp_path / "a" / "drive.json").resolve()), str(EXAMPLE_RIG)]
    assert [i.name for i in items] == ["a", "ex"]              # a drive file's folder names its scene
    assert items[0].detail() is not None and items[1].detail() is None
    assert items[1].keyframe_gap == 1.5 and items[0].options() != items[1].options()


@pytest.mark.parametrize("line, field, says", [
    ("{\"input\": ", "line 1", "not valid JSON"),
    ("{\"input\": \"EX\", \"keyframes_gap\": 1}", "line 1: keyframes_gap", "Extra inputs"),
    ("{\"input\": \"EX\", \"detail_stride\": 0}", "line 1: detail_stride", "1..64"),
    ("{\"input\": \"EX\", \"keyframe_spacing\": -1}", "line 1: keyframe_spacing", "greater than 0"),
    ("{\"input\": \"EX\", \"lidar\": \"yes\"}", "line 1: lidar", "boolean"),
    ("{\"input\": \"EX\", \"keyframes\": [3, 1]}", "line 1: keyframes", "increasing"),
    ("nowhere/drive.json", "line 1: input", "no file"),
    ("http://example.com/drive.json", "line 1: input", "s3://"),
    ("{\"input\": \"EX\", \"name\": \"has space\"}", "line 1: name", "1 to 200 characters"),
    ("EX\nEX", "line 2", "the same input and options as line 1"),
    ("EX\n{\"input\": \"EX\", \"detail_stride\": 4}", "line 2: name", "line 1's name too"),
    ("# nothing\n\n", "manifest", "lists no inputs"),
])
def test_manifest_errors_name_the_line_and_option(tmp_path, line, field, says):
    m = _manifest(tmp_path, line.replace("EX", str(EXAMPLE_RIG)))
    with pytest.raises(B.ManifestError) as e:
        B.read_manifest(m)
    assert e.value.field == field and says in e.value.message, str(e.value)
    assert e.value.where == m and isinstance(e.value, FieldError)


def test_a_missing_manifest_is_an_error_naming_it(tmp_path):
    with pytest.raises(B.ManifestError, match="cannot be read"):
        B.read_manifest(str(tmp_path / "none.txt"))


def test_default_names_and_results():
    from xyzcyl.server.commands.batch import default_results

    assert B.default_name("s3://b/drives/d17/drive.json") == "d17"
    assert B.default_name("/x/frame_00/rig.json") == "frame_00"
    assert B.default_name("/x/clip-3.json") == "clip-3"
    assert default_results("/m/drives.txt", "/store") == "/m/drives.results.jsonl"
    assert default_results("s3://b/m.jsonl", "s3://b/scenes") == "s3://b/scenes/batch-results.jsonl"


# ---------------------------------------------------------------------------------------------- the scene's key

def test_the_scene_key_follows_the_content_options_and_model(tmp_path):
    src = write_drive(tmp_path / "a", [pose(0), pose(2)], [0.0, 0.5])
    drive = B.load_input(src)
    files = B.input_files(drive)
    assert src in files and (tmp_path / "a" / "frame_01" / "rig.json") in files
    assert sum(p.suffix == ".png" for p in files) == 6            # one image per camera, named by both frames
    k = B.scene_key(drive, src.parent, {"lidar": True}, MODEL)
    assert B.scene_key(drive, src.parent, {"lidar": True}, MODEL) == k
    assert B.scene_key(drive, src.parent, {"lidar": False}, MODEL) != k
    assert B.scene_key(drive, src.parent, {"lidar": True}, {**MODEL, "version": "1.4.1"}) != k
    moved = tmp_path / "elsewhere"
    shutil.copytree(src.parent, moved)                           # the same drive at another path: the same key
    assert B.scene_key(B.load_input(moved / "drive.json"), moved, {"lidar": True}, MODEL) == k
    rig = json.loads((moved / "frame_01" / "rig.json").read_text())
    rig["cameras"][0]["cam_to_ego"][0][3] += 0.01                 # one calibration number changed: another key
    (moved / "frame_01" / "rig.json").write_text(json.dumps(rig))
    assert B.scene_key(B.load_input(moved / "drive.json"), moved, {"lidar": True}, MODEL) != k
    sid = B.scene_id_of(k)
    assert valid_id(sid) and sid == B.scene_id_of(k)


def test_a_rig_is_a_drive_of_one_frame():
    drive = B.load_input(EXAMPLE_RIG)
    assert len(drive) == 1 and drive.path is None
    files = B.input_files(drive)
    assert EXAMPLE_RIG in files and len(files) == 7              # rig.json and six images


# ---------------------------------------------------------------------------------------------- the store handles

def _scene_folder(tmp: Path) -> Path:
    d = tmp / "scene"
    d.mkdir(parents=True)
    (d / "scene.json").write_text("{}")
    (d / "scene.ply").write_bytes(b"ply" * 10)
    return d


FIELDS = {"cameras": [{"name": "CAM", "width": 8, "height": 4, "model": "pinhole"}],
          "detail": {"enabled": True, "stride": 2}, "name": "drive-a"}


def test_folder_store_handle_begins_retakes_commits_and_the_server_sees_it(tmp_path):
    store = tmp_path / "store"
    h = B.StoreHandle(str(store))
    sid = B.scene_id_of("cd" * 32)
    assert h.record(sid) is None
    h.begin(sid, FIELDS)
    assert h.record(sid).state == "running"
    other = B.StoreHandle(str(store))            # another process retakes a record a killed run left running
    other.begin(sid, FIELDS)
    rec = other.record(sid)
    assert rec.state == "running" and rec.name == "drive-a"
    work = other.work_dir()
    assert work.parent == store / "tmp" and work.name.startswith("batch-")
    done = other.store.commit(sid, _scene_folder(work), gaussians=5)
    assert done.state == "ready" and (store / "scenes" / sid / "scene.json").is_file()
    server = FolderStore(store)                   # `xyzcyl serve` opening the store afterwards: ready, not orphaned
    assert server.open()["ready"] == 1 and server.get(sid).gaussians == 5


def test_clean_work_removes_only_dead_runs_folders(tmp_path):
    import socket

    tmp = tmp_path / "store" / "tmp"
    host = socket.gethostname()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    (tmp / f"batch-{host}-{dead}-1").mkdir(parents=True)
    (tmp / f"batch-{host}-{os.getpid()}-2").mkdir()
    (tmp / "0123abcd").mkdir()                    # the server's own work folder: not the batch's to remove
    assert B.clean_work(str(tmp_path / "store")) == 1
    assert sorted(p.name for p in tmp.iterdir()) == sorted([f"batch-{host}-{os.getpid()}-2", "0123abcd"])


def test_s3_store_handle_and_inputs(bucket, tmp_path, monkeypatch):  # noqa: F811 - the moto fixture
    import boto3

    client = boto3.client("s3")
    h = B.StoreHandle(f"s3://{bucket}/scenes")
    sid = B.scene_id_of("ef" * 32)
    h.begin(sid, FIELDS)
    assert h.record(sid).state == "running" and h.record(sid).owner.startswith("xyzcyl-batch:")
    h.store.fail(sid, "error", "boom")
    h.begin(sid, FIELDS)                          # a failed record is retaken, not deleted (a tombstone would stay)
    assert h.record(sid).state == "running" and h.record(sid).error is None
    assert h.store.commit(sid, _scene_folder(h.work_dir()), gaussians=7).state == "ready"
    assert f"scenes/scenes/{sid}/scene.json" in [o["Key"] for o in client.list_objects_v2(
        Bucket=bucket, Prefix="scenes/scenes/")["Contents"]]
    # an input in S3: its folder fetched once into this node's cache
    for p in EXAMPLE_RIG.parent.rglob("*"):
        if p.is_file():
            client.upload_file(str(p), bucket, f"drives/ex/{p.relative_to(EXAMPLE_RIG.parent).as_posix()}")
    client.put_object(Bucket=bucket, Key="drives/other/rig.json", Body=b"{}")
    monkeypatch.setenv("XYZCYL_BATCH_CACHE", str(tmp_path / "cache"))
    local = B.fetch_input(f"s3://{bucket}/drives/ex/rig.json")
    assert local.name == "rig.json" and (local.parent / "images" / "CAM_FRONT.png").is_file()
    assert not (local.parent / "other").exists()
    assert B.fetch_input(f"s3://{bucket}/drives/ex/rig.json") == local
    drive = B.load_input(local)
    assert B.scene_key(drive, local.parent, {}, MODEL) == B.scene_key(B.load_input(EXAMPLE_RIG), EXAMPLE_RIG.parent,
                                                                      {}, MODEL)
    with pytest.raises(FileNotFoundError):
        B.fetch_input(f"s3://{bucket}/drives/ex/nothing.json")
    # the manifest and the results table in S3 too
    client.put_object(Bucket=bucket, Key="m/drives.txt", Body=b"../drives/ex/rig.json\n")
    items = B.read_manifest(f"s3://{bucket}/m/drives.txt")
    assert [i.input for i in items] == [f"s3://{bucket}/drives/ex/rig.json"] and items[0].name == "ex"
    table = B.Results(f"s3://{bucket}/out/results.jsonl")
    table.add({"status": "ready"})
    table.add({"status": "failed"})
    body = client.get_object(Bucket=bucket, Key="out/results.jsonl")["Body"].read().decode()
    assert [json.loads(x)["status"] for x in body.splitlines()] == ["ready", "failed"]


def test_default_sizes_keep_the_workers_within_cpus_and_memory():
    gib = 2**30
    # this machine: 2 CPUs, ~16 GiB for Ray: both CPUs make keyframes, one drive at once
    assert B.default_sizes(2, 16 * gib, 1, None, None)[:2] == (2, 1)
    # a 16-core laptop with ~20 GiB for Ray: the memory, not the cores, bounds the workers (and says so)
    w, d, why = B.default_sizes(16, 20 * gib, 1, None, None)
    assert (w, d) == (4, 1) and "not 16" in why                   # 4 x 3.7 + 3.7 = 18.5 GiB; 5 would be 22.2
    assert w * B.WORKER_BYTES + d * B.FUSION_BYTES <= 20 * gib < (w + 1) * B.WORKER_BYTES + d * B.FUSION_BYTES
    # a cluster with memory to spare: the CPUs (2 each) bound them
    assert B.default_sizes(64, 512 * gib, 2, None, None) == (32, 8, "")
    # what the user asks for is kept; a tiny machine still gets one of each
    assert B.default_sizes(16, 4 * gib, 1, 6, 3) == (6, 3, "")
    assert B.default_sizes(1, 1 * gib, 1, None, None)[:2] == (1, 1)


# ---------------------------------------------------------------------------------------------- failures

def test_failures_are_rows_with_the_services_codes():
    from xyzcyl.runtime.drive import DriveError

    f = B.failure_of(DriveError("frames[2].ego_to_world", "is missing", "d.json"))
    assert f["code"] == "invalid_input" and f["field"] == "frames[2].ego_to_world"
    assert B.failure_of(OSError(errno.ENOSPC, "No space left"))["code"] == "storage_full"
    assert B.failure_of(RuntimeError("x"))["code"] == "error"
    ray = pytest.importorskip("ray")
    wrapped = ray.exceptions.RayTaskError("keyframe", "traceback", DriveError("tracks[0]", "bad"))
    assert B.failure_of(wrapped)["field"] == "tracks[0]"


# ---------------------------------------------------------------------------------------------- the command

def _cli(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "xyzcyl", "batch", *args], capture_output=True, text=True,
                          timeout=120, **kw)


def test_the_command_refuses_bad_arguments_before_starting_ray(tmp_path):
    r = _cli(_manifest(tmp_path, "{\"input\": 3}\n"), "--out", str(tmp_path / "s"))
    assert r.returncode == 2 and "line 1: input" in r.stderr
    r = _cli(_manifest(tmp_path, str(EXAMPLE_RIG)), "--out", str(tmp_path / "s"), "--workers", "0")
    assert r.returncode == 2 and "--workers: must be >= 1" in r.stderr
    r = _cli(_manifest(tmp_path, str(EXAMPLE_RIG)), "--out", str(tmp_path / "s"), "--model", str(tmp_path))
    assert r.returncode == 2 and "--model" in r.stderr
    assert not (tmp_path / "s").exists()


def test_a_dry_run_plans_without_ray_and_writes_nothing(tmp_path):
    write_drive(tmp_path / "broken", [pose(0), pose(2)], [0.4, 0.0])
    m = _manifest(tmp_path, f"{EXAMPLE_RIG}\nbroken/drive.json\n")
    store = tmp_path / "store"
    r = _cli(m, "--out", str(store), "--dry-run", env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert r.returncode == 3, r.stderr                              # one input is bad
    assert "synth_nuscenes: to make (scene " in r.stderr and "broken: FAILED invalid_input" in r.stderr
    assert "dry run: 1 to make, 0 in the store, 1 failed" in r.stderr
    assert not store.exists() and not list(tmp_path.glob("*.results.jsonl"))
    # the scene in the store (as a batch leaves it, by its id): the dry run says it would be skipped
    sid = re.search(r"to make \(scene (\S+),", r.stderr).group(1)
    h = B.StoreHandle(str(store))
    h.begin(sid, FIELDS)
    h.store.commit(sid, _scene_folder(h.work_dir()), gaussians=9)
    r = _cli(m, "--out", str(store), "--dry-run")
    assert f"synth_nuscenes: skipped (scene {sid}, 9 Gaussians is in the store)" in r.stderr
    assert h.record(sid).name == "drive-a"                        # a dry run renames nothing


def _inputs(tmp_path: Path) -> tuple[str, list[str]]:
    """The manifest of three drives and a rig: a synthetic drive moving at 5 m/s, the shared PandaSet drive cut to
    frames 0 and 8 (its tracks kept; a second synthetic drive where the real data is absent), the example rig (a
    one-frame drive), and a drive whose frames are out of time order; the names in the manifest's order."""
    write_drive(tmp_path / "synth", [pose(0), pose(2), pose(4)], [0.0, 0.4, 0.8])
    real = ROOT.parent / "shared" / "data" / "real" / "pandaset_002_drive" / "drive.json"
    if os.environ.get("XYZCYL_REAL_DATA"):
        real = Path(os.environ["XYZCYL_REAL_DATA"]) / "pandaset_002_drive" / "drive.json"
    if real.is_file():
        cut_drive(real, [0, 8], tmp_path / "pandaset")
    else:
        write_drive(tmp_path / "pandaset", [pose(0), pose(0, 1.5)], [0.0, 0.3])
    write_drive(tmp_path / "broken", [pose(0), pose(2)], [0.4, 0.0])
    lines = [json.dumps({"input": "synth/drive.json", "detail_stride": 4}),
             json.dumps({"input": "pandaset/drive.json", "name": "pandaset-cut", "detail_stride": 4,
                         "keyframes": [0, 1]}),
             json.dumps({"input": str(EXAMPLE_RIG), "name": "rig", "detail_stride": 4}),
             "broken/drive.json"]
    return _manifest(tmp_path, "\n".join(lines) + "\n"), ["synth", "pandaset-cut", "rig", "broken"]


def _rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()] if path.is_file() else []


def _store_state(store: Path) -> dict[str, tuple]:
    out = {}
    for p in sorted((store / "records").glob("*.json")):
        rec = json.loads(p.read_text())
        scene = store / "scenes" / rec["id"] / "scene.json"
        out[rec["id"]] = (rec["name"], rec["state"], rec.get("gaussians"),
                          scene.stat().st_mtime_ns if scene.is_file() else None)
    return out


@pytest.mark.heavy      # Ray started three times in subprocesses: ~3 minutes of CI's 15 on 2 cores
@pytest.mark.timeout(900)
def test_batch_on_local_ray_killed_and_run_again(tmp_path):
    """Three drives, one broken, and a rig on a local Ray: the run is killed (SIGKILL to its process group: Ray's
    processes too) once the first scene is in the store; the next run finishes the others and skips that one (its
    files not rewritten); the store then holds the three ready scenes the manifest names (the ids its inputs,
    options and the model make), one error is in the table, the exit status is 3 (partial); a third run skips all
    three and rewrites nothing."""
    pytest.importorskip("ray")
    manifest, names = _inputs(tmp_path)
    store, results = tmp_path / "store", tmp_path / "results.jsonl"
    # one keyframe worker: its model loads while the plan step runs (the test's CI has 2 cores)
    argv = [sys.executable, "-m", "xyzcyl", "batch", manifest, "--out", str(store), "--results", str(results),
            "--workers", "1", "--quiet"]
    log = open(tmp_path / "run1.log", "w")
    proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and proc.poll() is None:
            if any(r["status"] == "ready" for r in _rows(results)):
                break
            time.sleep(0.2)
        assert proc.poll() is None, (tmp_path / "run1.log").read_text()[-3000:]
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)
        log.close()
    first = [r for r in _rows(results) if r["status"] == "ready"]
    assert first, (tmp_path / "run1.log").read_text()[-3000:]
    before = _store_state(store)
    assert before[first[0]["scene_id"]][1] == "ready"

    run2 = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert run2.returncode == 3, run2.stderr[-3000:]                  # partial: one failed, the others done
    rows = {r["name"]: r for r in _rows(results)}
    assert sorted(rows) == sorted(names)
    assert rows[first[0]["name"]]["status"] == "skipped"               # made by the killed run, kept
    assert {rows[n]["status"] for n in names[:3]} <= {"ready", "skipped"}
    err = rows["broken"]["error"]
    assert rows["broken"]["status"] == "failed" and err["code"] == "invalid_input"
    assert err["field"] == "frames[1].timestamp_s" and "broken" in err["message"]
    assert "done: " in run2.stderr and "1 failed" in run2.stderr
    after = _store_state(store)
    ready = {rows[n]["scene_id"] for n in names[:3]}
    from xyzcyl.runtime.inference import default_model_dir, read_model_info, scene_model_of

    model = scene_model_of(read_model_info(default_model_dir()))
    expected = {B.scene_id_of(B.scene_key(B.load_input(Path(i.input)), Path(i.input).parent, i.options(), model))
                for i in B.read_manifest(manifest)[:3]}
    assert ready == expected                                                      # the manifest's scenes
    assert set(after) == ready and all(v[1] == "ready" for v in after.values())   # no record left running
    assert after[first[0]["scene_id"]] == before[first[0]["scene_id"]]           # not rewritten
    assert not list((store / "tmp").iterdir())                                    # no work folder left
    from xyzcyl.runtime.scene import Scene

    for sid in ready:
        scene = Scene.load(store / "scenes" / sid)
        assert len(scene.gaussians) == after[sid][2] > 0
        if after[sid][0] == "rig":
            assert scene.drive is None and rows["rig"]["frames"] == 1
        else:
            assert scene.drive is not None and scene.drive["frames"] == rows[after[sid][0]]["frames"]

    run3 = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert run3.returncode == 3, run3.stderr[-3000:]
    assert {r["name"]: r["status"] for r in _rows(results)} == {names[0]: "skipped", names[1]: "skipped",
                                                                 names[2]: "skipped", "broken": "failed"}
    assert _store_state(store) == after                                          # nothing rewritten
