"""deploy/kubernetes.yaml (xyzcyl serve: Secret, Deployment, Service) and deploy/rayjob.yaml (xyzcyl batch on
a KubeRay RayJob) are not run here (no cluster reachable, docs/deploy.md "What is tested"), so their
structure is checked instead: what would let `kubectl apply` succeed and the pods still misbehave. An
`XYZCYL_*` variable that is no setting (pydantic's extra="forbid": the server refuses to start), a Ray
container on another image (the driver and the workers must run the same code), an entrypoint flag that
`xyzcyl batch` does not take (the job fails after the cluster is up), a container without the S3
credentials, work scheduled on the head, a memory limit below the request (the API server rejects the pod),
numba without a writable cache folder (the kernels do not import)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys

import pytest
from xyzcyl.testing import REPO

yaml = pytest.importorskip("yaml")

KUBERNETES = REPO / "deploy" / "kubernetes.yaml"
RAYJOB = REPO / "deploy" / "rayjob.yaml"
IMAGE = "xyzcyl:batch"
SECRET = "xyzcyl-s3"

_UNITS = {"": 1, "k": 10**3, "M": 10**6, "G": 10**9, "T": 10**12,
          "Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40}


def _bytes(quantity) -> int:
    """A Kubernetes memory quantity ("12Gi", "1280Mi", "2G", 2147483648) in bytes."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([kMGT]i?|Ki)?", str(quantity))
    assert m, f"not a memory quantity: {quantity!r}"
    return int(float(m.group(1)) * _UNITS[m.group(2) or ""])


def _documents(path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d is not None]


def _one(docs: list[dict], kind: str) -> dict:
    found = [d for d in docs if d.get("kind") == kind]
    assert len(found) == 1, f"expected one {kind}, found {len(found)}"
    return found[0]


def _deployment_pod() -> dict:
    return _one(_documents(KUBERNETES), "Deployment")["spec"]["template"]["spec"]


def _rayjob() -> dict:
    docs = _documents(RAYJOB)
    assert len(docs) == 1, "deploy/rayjob.yaml holds the RayJob only"
    return docs[0]


def _ray_pods() -> list[tuple[str, dict, dict]]:
    """(group name, rayStartParams, pod spec) of the head group and of every worker group."""
    cluster = _rayjob()["spec"]["rayClusterSpec"]
    head = cluster["headGroupSpec"]
    pods = [("head", head.get("rayStartParams", {}), head["template"]["spec"])]
    workers = cluster.get("workerGroupSpecs") or []
    assert workers, "the RayJob needs a worker group: the head runs no work (num-cpus 0)"
    pods += [(g["groupName"], g.get("rayStartParams", {}), g["template"]["spec"]) for g in workers]
    return pods


def _containers(pod: dict) -> list[dict]:
    return list(pod.get("initContainers") or []) + list(pod["containers"])


def _all_containers() -> list[tuple[str, dict, dict]]:
    """(where, container, its pod spec) of every container of both files."""
    out = [("kubernetes.yaml", c, _deployment_pod()) for c in _containers(_deployment_pod())]
    for group, _params, pod in _ray_pods():
        out += [(f"rayjob.yaml {group}", c, pod) for c in _containers(pod)]
    return out


def _env(container: dict) -> dict[str, str]:
    return {e["name"]: e.get("value") for e in container.get("env") or []}


def _uses_secret(container: dict, name: str) -> bool:
    from_env = any((e.get("valueFrom") or {}).get("secretKeyRef", {}).get("name") == name
                   for e in container.get("env") or [])
    from_all = any((s.get("secretRef") or {}).get("name") == name for s in container.get("envFrom") or [])
    return from_env or from_all


# ---- deploy/kubernetes.yaml


def test_kubernetes_has_the_secret_the_deployment_and_the_service():
    docs = _documents(KUBERNETES)
    assert sorted(d["kind"] for d in docs) == ["Deployment", "Secret", "Service"]
    secret, deployment, service = (_one(docs, k) for k in ("Secret", "Deployment", "Service"))
    assert secret["metadata"]["name"] == SECRET
    assert {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"} <= set(secret["stringData"])
    # the Deployment owns its pods and the Service reaches them: both selectors match the pod labels
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    for selector in (deployment["spec"]["selector"]["matchLabels"], service["spec"]["selector"]):
        assert selector.items() <= labels.items(), f"selector {selector} does not match the pods {labels}"
    # the Service's named targetPort is a port the container declares
    names = {p.get("name") for c in _deployment_pod()["containers"] for p in c.get("ports") or []}
    assert {p["targetPort"] for p in service["spec"]["ports"]} <= names
    for c in _deployment_pod()["containers"]:
        assert _uses_secret(c, SECRET), f"container {c['name']} does not take the credentials of {SECRET}"


def test_kubernetes_env_names_are_server_settings():
    """Each XYZCYL_<NAME> is a field `name` of server/settings.py's Settings, and its value is valid there."""
    settings = pytest.importorskip("xyzcyl.server.settings")
    fields = set(settings.Settings.model_fields)
    values = {}
    for c in _deployment_pod()["containers"]:
        for name, value in _env(c).items():
            if name.startswith("XYZCYL_"):
                field = name.removeprefix("XYZCYL_").lower()
                assert field in fields, f"{name} is not a setting of server/settings.py"
                values[field] = value
    assert "store" in values, "the replicas share the s3:// store through XYZCYL_STORE"
    assert values["store"].startswith("s3://")
    settings.Settings(**values)      # pydantic raises on a value the server would refuse at start


# ---- deploy/rayjob.yaml


def test_rayjob_is_a_kuberay_rayjob():
    job = _rayjob()
    assert (job["apiVersion"], job["kind"]) == ("ray.io/v1", "RayJob")
    spec = job["spec"]
    assert spec["submissionMode"] == "K8sJobMode"
    assert spec["shutdownAfterJobFinishes"] is True
    assert isinstance(spec["ttlSecondsAfterFinished"], int) and spec["ttlSecondsAfterFinished"] >= 0
    assert re.fullmatch(r"2\.\d+\.\d+", spec["rayClusterSpec"]["rayVersion"])
    # the CRD types rayStartParams as map[string]string: a bare YAML number is rejected by the API server
    for group, params, _pod in _ray_pods():
        bad = {k: v for k, v in params.items() if not isinstance(v, str)}
        assert not bad, f"{group}: rayStartParams values must be quoted strings: {bad}"


def test_every_ray_container_runs_the_batch_image():
    for group, _params, pod in _ray_pods():
        for c in _containers(pod):
            assert c["image"] == IMAGE, f"{group}/{c['name']} runs {c['image']}, not {IMAGE}"


def _entrypoint() -> list[str]:
    return shlex.split(_rayjob()["spec"]["entrypoint"])


def test_the_entrypoint_is_xyzcyl_batch():
    words = _entrypoint()
    assert words[:2] == ["xyzcyl", "batch"], words
    assert not words[2].startswith("-"), "the manifest comes first"
    flags = {w.split("=")[0] for w in words if w.startswith("--")}
    assert {"--out", "--results"} <= flags, "scenes go to the store, the results table to the bucket"


def test_the_entrypoint_flags_are_ones_xyzcyl_batch_takes():
    flags = sorted({w.split("=")[0] for w in _entrypoint() if w.startswith("-")})
    assert flags
    r = subprocess.run([sys.executable, "-m", "xyzcyl", "batch", "--help"], cwd=REPO, capture_output=True,
                       text=True, timeout=120, check=False)
    if r.returncode != 0 and "invalid choice: 'batch'" in r.stderr:
        pytest.xfail("batch command not yet present")
    assert r.returncode == 0, r.stderr
    unknown = [f for f in flags if not re.search(rf"(?<![\w-]){re.escape(f)}(?![\w-])", r.stdout)]
    assert not unknown, f"`xyzcyl batch --help` does not list {unknown}"


def test_every_ray_container_takes_the_s3_secret():
    assert _one(_documents(KUBERNETES), "Secret")["metadata"]["name"] == SECRET, "the Secret the RayJob names"
    for group, _params, pod in _ray_pods():
        for c in pod["containers"]:
            assert _uses_secret(c, SECRET), f"{group}/{c['name']} does not take the credentials of {SECRET}"


def test_the_head_runs_no_work():
    head = [params for group, params, _pod in _ray_pods() if group == "head"][0]
    assert head.get("num-cpus") == "0"
    assert all(params.get("num-cpus") != "0" for group, params, _pod in _ray_pods() if group != "head")


def test_memory_limits_hold_the_requests():
    for where, c, _pod in _all_containers():
        res = c.get("resources") or {}
        limit, request = (res.get(k, {}).get("memory") for k in ("limits", "requests"))
        assert limit is not None, f"{where}/{c['name']}: no memory limit"
        assert request is None or _bytes(limit) >= _bytes(request), f"{where}/{c['name']}: limit < request"


def _volume_for(pod: dict, container: dict, path: str) -> tuple[dict, dict]:
    """The volumeMount whose mountPath is `path` or its closest parent, and that mount's volume."""
    mounts = [m for m in container.get("volumeMounts") or []
              if path == m["mountPath"] or path.startswith(m["mountPath"].rstrip("/") + "/")]
    assert mounts, f"{container['name']}: nothing is mounted at {path}"
    mount = max(mounts, key=lambda m: len(m["mountPath"]))
    volumes = {v["name"]: v for v in pod.get("volumes") or []}
    assert mount["name"] in volumes, f"{container['name']}: mount {mount['name']} has no volume"
    return mount, volumes[mount["name"]]


def test_numba_has_a_writable_cache_folder():
    """numba's cache=True writes next to the package unless NUMBA_CACHE_DIR names a folder; the venv is
    read-only to the pods' uid, so the folder must be a mounted emptyDir, not read-only."""
    for group, _params, pod in _ray_pods():
        for c in pod["containers"]:
            path = _env(c).get("NUMBA_CACHE_DIR")
            assert path and path.startswith("/"), f"{group}/{c['name']}: NUMBA_CACHE_DIR is not set"
            mount, volume = _volume_for(pod, c, path)
            assert not mount.get("readOnly"), f"{group}: {path} is mounted read-only"
            assert "emptyDir" in volume, f"{group}: {path} is not on an emptyDir"


def test_the_object_store_fits_in_dev_shm():
    """Ray's object store is /dev/shm: a memory emptyDir at least as large as object-store-memory (where set),
    within the container's memory limit (tmpfs pages count against it)."""
    for group, params, pod in _ray_pods():
        c = pod["containers"][0]
        _mount, volume = _volume_for(pod, c, "/dev/shm")
        assert volume["emptyDir"].get("medium") == "Memory", f"{group}: /dev/shm is not memory-backed"
        size = _bytes(volume["emptyDir"]["sizeLimit"])
        limit = _bytes(c["resources"]["limits"]["memory"])
        assert size <= limit, f"{group}: /dev/shm is larger than the memory limit"
        if "object-store-memory" in params:
            assert size >= int(params["object-store-memory"]), f"{group}: the object store exceeds /dev/shm"
