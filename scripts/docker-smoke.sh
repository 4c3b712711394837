#!/usr/bin/env bash
# scripts/docker-smoke.sh: build the service image (Dockerfile) with podman, run it, post the example rig, render a
# view, stop it with SIGTERM while a batch render is in flight, and print one JSON document of figures on stdout
# (image size, cold start to ready, reconstruction and render times, exit code). Progress goes to stderr; the
# rendered PNG, the responses and the container's log are left in $XYZCYL_SMOKE_OUT (default: a new temp dir).
#
#   bash scripts/docker-smoke.sh > docs/deploy-smoke.json
#
# Needs root (or a working rootless podman) and: podman, runc, curl, python3 (host side, standard library only);
# debootstrap when the base image has to be made (below). Missing ones are installed from Debian with apt-get
# (podman runc uidmap fuse-overlayfs slirp4netns debootstrap) when apt-get is there.
#
# Why a locally made base image: the Dockerfile's base is python:3.11-slim from an image registry. Where no image
# registry can be reached (a sandbox whose network reaches only the Debian and PyPI package mirrors, as here),
# `podman pull` fails, so this script makes a stand-in once and reuses it afterwards:
#   1. debootstrap --variant=minbase Debian bookworm (its python3 is 3.11) with python3, python3-venv,
#      python-is-python3 and ca-certificates into a temp dir, from the Debian mirror ($XYZCYL_DEBIAN_MIRROR);
#   2. copy this host's extra CA certificates (/usr/local/share/ca-certificates/*.crt) in and run
#      update-ca-certificates: where HTTPS to PyPI goes through an intercepting egress proxy, pip inside the
#      build needs its CA (a real python:3.11-slim on an open network needs nothing of the kind);
#   3. drop apt lists, docs, man pages; `tar | podman import` it as localhost/python:3.11-slim with
#      PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin (python and python3 are /usr/bin's),
#      LANG=C.UTF-8 and CMD python3, like the real image.
# The build then gets --build-arg PYTHON_IMAGE=localhost/python:3.11-slim. The Dockerfile itself is the same for
# both bases: it makes its venv with `python3 -m venv` and runs everything from /opt/venv/bin. When
# docker.io/library/python:3.11-slim is present or can be pulled, it is used instead and nothing is debootstrapped.
#
# podman notes (podman 4.3 from Debian bookworm, as root, cgroup v1, on this machine):
#   - `podman build --format docker`: the default OCI format has no HEALTHCHECK field and podman drops it;
#   - `podman run --ulimit nofile=H:H --ulimit nproc=32768:32768` with H = `ulimit -Hn` (added by this script when
#     H < 1048576): podman asks runc for RLIMIT_NOFILE 1048576 by default, above this sandbox's hard limit (20000;
#     no CAP_SYS_RESOURCE to raise it), and every run failed with "error setting rlimits for ready process: error
#     setting rlimit type 7: operation not permitted"; with nofile alone it then asks for the host's RLIMIT_NPROC
#     (96365) and fails on type 6 instead; 32768 (podman's own default) works. `--ulimit host` was ignored by
#     podman 4.3. The build's RUN steps were not affected;
#   - no systemd here: podman logs "level=error ... unable to get systemd connection to add/start/remove
#     healthchecks" for a container with a HEALTHCHECK (harmless: no timer runs the check; this script runs it
#     once with `podman healthcheck run`);
#   - the OCI runtime is runc, chosen by this script (`podman --runtime PATH-OF-RUNC`, installed with apt-get when
#     absent): Debian's podman may come with crun alone, and crun fails on a cgroup v1 / hybrid host ("cgroups in
#     hybrid mode not supported"); runc works on both. A `--runtime` in XYZCYL_PODMAN_FLAGS wins; without runc and
#     without apt-get, podman's own default is used (with a warning);
#   - otherwise the defaults worked (overlay storage, cgroupfs manager, netavark bridge network for the
#     build's pip and for -p 127.0.0.1:PORT:8000); where they do not, set XYZCYL_PODMAN_FLAGS (global flags, e.g.
#     "--cgroup-manager=cgroupfs --storage-driver=vfs"), XYZCYL_BUILD_FLAGS (e.g. "--isolation=chroot
#     --network=host") and XYZCYL_RUN_FLAGS (more `podman run` flags).
# A whole run here, debootstrap and build included, took about 4.5 minutes (2 shared cores); the figures of that
# run are docs/deploy-smoke.json, and docs/docker.md describes the image.
#
# The image built on the local base also trusts the CA certificates of step 2: it is for this test, not for
# publishing; build the published image on the real python:3.11-slim.
#
# Environment: XYZCYL_IMAGE (tag to build, default localhost/xyzcyl:smoke), XYZCYL_SMOKE_OUT, XYZCYL_SKIP_BUILD=1
# (test an image already built), XYZCYL_REBUILD_BASE=1 (make the local base again), XYZCYL_DEBIAN_MIRROR.
# Every wait is bounded; the container and its volume are removed on exit, whatever happens.
set -euo pipefail
cd "$(dirname "$0")/.."

IMAGE=${XYZCYL_IMAGE:-localhost/xyzcyl:smoke}
BASE_REMOTE=docker.io/library/python:3.11-slim
BASE_LOCAL=localhost/python:3.11-slim
MIRROR=${XYZCYL_DEBIAN_MIRROR:-http://deb.debian.org/debian}
OUT=${XYZCYL_SMOKE_OUT:-$(mktemp -d /tmp/xyzcyl-smoke.XXXXXX)}
mkdir -p "$OUT"
read -r -a PODMAN_FLAGS <<< "${XYZCYL_PODMAN_FLAGS:-}"
read -r -a BUILD_FLAGS <<< "${XYZCYL_BUILD_FLAGS:-}"
read -r -a RUN_FLAGS <<< "${XYZCYL_RUN_FLAGS:-}"
CTR=xyzcyl-smoke-$$
VOL=xyzcyl-smoke-$$
ROOTFS=
CAMS=(CAM_FRONT CAM_FRONT_RIGHT CAM_BACK_RIGHT CAM_BACK CAM_BACK_LEFT CAM_FRONT_LEFT)

log() { echo "[docker-smoke $(date +%T)] $*" >&2; }
die() { log "FAIL: $*"; exit 1; }
pm() { podman "${PODMAN_FLAGS[@]}" "$@"; }
now() { date +%s.%N; }
since() { python3 -c "import sys; print(round(float(sys.argv[2]) - float(sys.argv[1]), 3))" "$1" "$(now)"; }

cleanup() {
    local rc=$?
    set +e
    if pm container exists "$CTR" 2>/dev/null; then
        pm logs "$CTR" > "$OUT/container.log" 2>&1
        pm rm -f -t 0 "$CTR" > /dev/null 2>&1
    fi
    pm volume rm -f "$VOL" > /dev/null 2>&1
    if [ -n "$ROOTFS" ] && [ -d "$ROOTFS" ]; then
        umount -R "$ROOTFS/proc" "$ROOTFS/sys" "$ROOTFS/dev/pts" 2> /dev/null
        rm -rf --one-file-system "$ROOTFS"
    fi
    [ "$rc" = 0 ] || log "exit $rc; container log and responses in $OUT"
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# ---- tools
# the OCI runtime named in XYZCYL_PODMAN_FLAGS (--runtime X or --runtime=X), if any
flag_runtime() {
    local i
    for ((i = 0; i < ${#PODMAN_FLAGS[@]}; i++)); do
        case "${PODMAN_FLAGS[i]}" in
            --runtime=*) echo "${PODMAN_FLAGS[i]#--runtime=}"; return 0 ;;
            --runtime) echo "${PODMAN_FLAGS[i + 1]:-}"; return 0 ;;
        esac
    done
    return 1
}
need=()
command -v podman > /dev/null || need+=(podman)
# runc, even where crun is there: see "podman notes" above
if ! flag_runtime > /dev/null && ! command -v runc > /dev/null; then need+=(runc); fi
command -v curl > /dev/null || need+=(curl)
command -v python3 > /dev/null || die "python3 is needed on the host (standard library only)"
if [ ${#need[@]} -gt 0 ]; then
    if command -v apt-get > /dev/null; then
        log "installing ${need[*]} uidmap fuse-overlayfs slirp4netns from Debian"
        timeout 600 apt-get update -q > "$OUT/apt.log" 2>&1 || true
        DEBIAN_FRONTEND=noninteractive timeout 900 apt-get install -y -q --no-install-recommends \
            "${need[@]}" uidmap fuse-overlayfs slirp4netns containernetworking-plugins >> "$OUT/apt.log" 2>&1 \
            || die "apt-get install failed (see $OUT/apt.log)"
    elif [ "${need[*]}" = runc ]; then
        log "WARNING: no runc and no apt-get to install it: podman's default OCI runtime is used (crun fails on a" \
            "cgroup v1 / hybrid host; XYZCYL_PODMAN_FLAGS=\"--runtime PATH\" chooses one)"
    else
        die "missing: ${need[*]} (install podman and runc)"
    fi
fi
if RUNTIME=$(flag_runtime); then
    log "OCI runtime $RUNTIME (XYZCYL_PODMAN_FLAGS)"
elif RUNTIME=$(command -v runc); then
    PODMAN_FLAGS=(--runtime "$RUNTIME" "${PODMAN_FLAGS[@]}")
    log "OCI runtime $RUNTIME (podman --runtime)"
else
    RUNTIME="podman's default"
fi
log "$(podman --version); out: $OUT"

# ---- the base image
make_local_base() {
    if ! command -v debootstrap > /dev/null; then
        command -v apt-get > /dev/null || die "no image registry and no debootstrap to make a base image"
        log "installing debootstrap from Debian"
        DEBIAN_FRONTEND=noninteractive timeout 600 apt-get install -y -q debootstrap >> "$OUT/apt.log" 2>&1 \
            || die "apt-get install debootstrap failed (see $OUT/apt.log)"
    fi
    ROOTFS=$(mktemp -d /var/tmp/xyzcyl-base.XXXXXX)
    log "debootstrapping Debian bookworm (python3.11) into $ROOTFS from $MIRROR (a few minutes)"
    timeout 1500 debootstrap --variant=minbase --include=python3,python3-venv,python-is-python3,ca-certificates \
        bookworm "$ROOTFS" "$MIRROR" > "$OUT/debootstrap.log" 2>&1 \
        || die "debootstrap failed: $(tail -n 5 "$OUT/debootstrap.log")"
    local n=0 crt
    for crt in /usr/local/share/ca-certificates/*.crt; do
        [ -f "$crt" ] || continue
        cp "$crt" "$ROOTFS/usr/local/share/ca-certificates/"
        n=$((n + 1))
    done
    if [ "$n" -gt 0 ]; then
        log "adding this host's $n extra CA certificate(s) to the base (an intercepting egress proxy's)"
        chroot "$ROOTFS" update-ca-certificates > /dev/null 2>&1 || die "update-ca-certificates failed in the base"
    fi
    chroot "$ROOTFS" apt-get clean
    rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/var/log/*.log \
        "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/* "$ROOTFS"/tmp/*
    chroot "$ROOTFS" python3 -c 'import sys, venv, ensurepip, ssl; assert sys.version_info[:2] == (3, 11)' \
        || die "the debootstrapped base has no usable python3.11 with venv"
    log "importing it as $BASE_LOCAL"
    tar --numeric-owner -C "$ROOTFS" -cf - . | pm import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["python3"]' \
        --message "debootstrap bookworm minbase + python3 python3-venv python-is-python3 ca-certificates" \
        - "$BASE_LOCAL" > /dev/null 2>&1 || die "podman import failed"
    rm -rf --one-file-system "$ROOTFS"
    ROOTFS=
}

BASE_KIND=registry
if [ "${XYZCYL_SKIP_BUILD:-0}" != 1 ]; then
    if pm image exists "$BASE_REMOTE"; then
        BASE=$BASE_REMOTE
    elif log "pulling $BASE_REMOTE" && timeout 300 podman "${PODMAN_FLAGS[@]}" pull -q "$BASE_REMOTE" \
            > "$OUT/pull.log" 2>&1; then
        BASE=$BASE_REMOTE
    else
        log "no image registry: $(tail -n 1 "$OUT/pull.log")"
        BASE=$BASE_LOCAL
        BASE_KIND=local-debootstrap
        if [ "${XYZCYL_REBUILD_BASE:-0}" = 1 ] || ! pm image exists "$BASE_LOCAL"; then
            make_local_base
        else
            log "reusing $BASE_LOCAL (XYZCYL_REBUILD_BASE=1 makes it again)"
        fi
    fi

    # ---- the image
    log "building $IMAGE from $BASE (pip install '.[server]'; several minutes on a cold cache)"
    t=$(now)
    timeout 2400 podman "${PODMAN_FLAGS[@]}" build --format docker "${BUILD_FLAGS[@]}" \
        --build-arg PYTHON_IMAGE="$BASE" -t "$IMAGE" -f Dockerfile . > "$OUT/build.log" 2>&1 \
        || die "podman build failed: $(tail -n 20 "$OUT/build.log")"
    BUILD_S=$(since "$t")
    log "built in ${BUILD_S} s"
else
    BASE=unknown
    BUILD_S=None
    pm image exists "$IMAGE" || die "XYZCYL_SKIP_BUILD=1 but there is no image $IMAGE"
fi
IMAGE_BYTES=$(pm image inspect --format '{{.Size}}' "$IMAGE")
BASE_BYTES=null
[ "$BASE" = unknown ] || BASE_BYTES=$(pm image inspect --format '{{.Size}}' "$BASE")

# ---- what is in the image
# podman asks runc for RLIMIT_NOFILE 1048576 by default; where this process's hard limit is lower (20000 here) runc
# fails: "error setting rlimits for ready process: error setting rlimit type 7: operation not permitted".
# Once nofile is given, podman also asks for the host's RLIMIT_NPROC, which failed the same way (type 6) above
# 32768 here, podman's own default: both are given.
hard_nofile=$(ulimit -Hn)
if [ "$hard_nofile" != unlimited ] && [ "$hard_nofile" -lt 1048576 ]; then
    nproc=$(ulimit -Hu)
    if [ "$nproc" = unlimited ] || [ "$nproc" -gt 32768 ]; then nproc=32768; fi
    RUN_FLAGS=(--ulimit "nofile=$hard_nofile:$hard_nofile" --ulimit "nproc=$nproc:$nproc" "${RUN_FLAGS[@]}")
    log "run flags ${RUN_FLAGS[*]} (the hard RLIMIT_NOFILE here is below podman's default 1048576)"
fi
crun_() { timeout 120 podman "${PODMAN_FLAGS[@]}" run --rm --no-healthcheck "${RUN_FLAGS[@]}" "$IMAGE" "$@"; }
crun_ true || die "podman cannot run the image (flags: ${PODMAN_FLAGS[*]} ${RUN_FLAGS[*]})"
TORCH=$(crun_ python -c 'import importlib.util as u; print(u.find_spec("torch") is not None)') \
    || die "python failed in the image"
[ "$TORCH" = False ] || die "torch is in the image"
if crun_ python -c 'import torch' > /dev/null 2>&1; then die "torch imports in the image"; fi
crun_ pip list --format=freeze > "$OUT/pip-list.txt" 2> /dev/null || die "pip list failed in the image"
if grep -qi '^torch' "$OUT/pip-list.txt"; then die "pip list has torch"; fi
WHOAMI=$(crun_ id -u)
[ "$WHOAMI" = 10001 ] || die "the image runs as uid $WHOAMI, not 10001"
MODEL_DIR=$(crun_ python -c 'from xyzcyl.runtime.inference import default_model_dir as d; print(d())')
[ "$MODEL_DIR" = /opt/xyzcyl/models/xyzcyl-cpu-v1 ] || die "the model is found at $MODEL_DIR"
VENV_MB=$(crun_ du -sm /opt/venv | cut -f1)
PYVER=$(crun_ python -c 'import platform; print(platform.python_version())')
log "image: $IMAGE_BYTES bytes, venv $VENV_MB MB, python $PYVER, uid $WHOAMI, no torch, model at $MODEL_DIR"

# ---- run it
PORT=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
S=http://127.0.0.1:$PORT
pm volume create "$VOL" > /dev/null
log "podman run -p 127.0.0.1:$PORT:8000 -v $VOL:/data"
t_run=$(now)
pm run -d --name "$CTR" -p "127.0.0.1:$PORT:8000" -v "$VOL:/data" "${RUN_FLAGS[@]}" "$IMAGE" > /dev/null \
    || die "podman run failed"
COLD_S=
for _ in $(seq 1 900); do   # 180 s at 0.2 s
    code=$(curl -s -o /dev/null -w '%{http_code}' --max-time 2 "$S/v2/health/ready" || true)
    if [ "$code" = 200 ]; then COLD_S=$(since "$t_run"); break; fi
    running=$(pm inspect --format '{{.State.Running}}' "$CTR" 2> /dev/null || echo false)
    [ "$running" = true ] || die "the container exited before ready: $(pm logs --tail 30 "$CTR" 2>&1)"
    sleep 0.2
done
[ -n "$COLD_S" ] || die "/v2/health/ready not 200 within 180 s: $(pm logs --tail 30 "$CTR" 2>&1)"
log "ready ${COLD_S} s after podman run"
[ "$(curl -s -o /dev/null -w '%{http_code}' --max-time 5 "$S/v2/health/live")" = 200 ] || die "/v2/health/live"
HEALTH=unsupported
if timeout 60 podman "${PODMAN_FLAGS[@]}" healthcheck run "$CTR" > "$OUT/healthcheck.log" 2>&1; then
    HEALTH=healthy
elif grep -qi 'unhealthy' "$OUT/healthcheck.log"; then
    die "HEALTHCHECK says unhealthy: $(cat "$OUT/healthcheck.log")"
fi

# ---- reconstruct the example rig (multipart as in docs/api.md)
parts=(-F "rig=@examples/synth_nuscenes/rig.json")
for c in "${CAMS[@]}"; do parts+=(-F "$c=@examples/synth_nuscenes/images/$c.png"); done
log "POST /v1/scenes?wait=240 (the example rig, 6 cameras)"
t=$(now)
code=$(curl -s -o "$OUT/scene.json" -w '%{http_code}' --max-time 300 -X POST "$S/v1/scenes?wait=240" "${parts[@]}")
RECON_WALL_S=$(since "$t")
[ "$code" = 201 ] || die "POST /v1/scenes answered $code: $(head -c 600 "$OUT/scene.json")"
read -r SID STATE GAUSS RECON_S < <(python3 -c '
import json, sys
s = json.load(open(sys.argv[1]))
print(s["id"], s["state"], s["gaussians"], s["timings"]["total"])' "$OUT/scene.json")
[ "$STATE" = ready ] || die "scene $SID is $STATE"
log "scene $SID ready: $GAUSS Gaussians, ${RECON_S} s in the worker, ${RECON_WALL_S} s for the request"

# ---- render CAM_FRONT (the first render also compiles the numba kernels into NUMBA_CACHE_DIR), then another
render() {   # render CAMERA FILE -> "code seconds"
    curl -s -o "$2" -w '%{http_code} %{time_total}\n' --max-time 300 "$S/v1/scenes/$SID/render?camera=$1"
}
read -r code RENDER_S < <(render CAM_FRONT "$OUT/CAM_FRONT.png")
[ "$code" = 200 ] || die "render CAM_FRONT answered $code: $(head -c 600 "$OUT/CAM_FRONT.png")"
read -r code RENDER2_S < <(render CAM_BACK "$OUT/CAM_BACK.png")
[ "$code" = 200 ] || die "render CAM_BACK answered $code"
PNG=$(python3 - "$OUT/CAM_FRONT.png" << 'EOF'
import struct, sys, zlib
b = open(sys.argv[1], "rb").read()
assert b[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
w, h, depth, ctype = struct.unpack(">IIBB", b[16:26])
assert (w, h) == (800, 450), f"{w}x{h}, not 800x450"
assert (depth, ctype) == (8, 2), f"bit depth {depth}, colour type {ctype}: not 8-bit RGB"
idat, i = b"", 8
while i < len(b):
    n, kind = struct.unpack(">I4s", b[i:i + 8])
    if kind == b"IDAT":
        idat += b[i + 8:i + 8 + n]
    i += 12 + n
raw = zlib.decompress(idat)
assert len(raw) == h * (1 + 3 * w), "truncated image data"
assert len(set(raw)) > 64, "a flat image"
print(f"{w}x{h} 8-bit RGB, {len(b)} bytes, {len(set(raw))} distinct byte values")
EOF
) || die "the rendered PNG: $PNG"
log "renders: CAM_FRONT ${RENDER_S} s ($PNG), CAM_BACK ${RENDER2_S} s"

# ---- SIGTERM while a batch render is in flight: it must finish (200, a whole zip), then exit 0
python3 -c '
import json, sys
cams = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]
print(json.dumps({"cameras": [{"camera": c, "width": 640 + 16 * i} for i in range(4) for c in cams]}))
' > "$OUT/batch.json"
curl -s -o "$OUT/batch.zip" -w '%{http_code}' --max-time 120 -X POST -H 'Content-Type: application/json' \
    --data-binary "@$OUT/batch.json" "$S/v1/scenes/$SID/render" > "$OUT/batch.code" 2> /dev/null &
BATCH_PID=$!
sleep 0.5
log "podman stop -t 35 (SIGTERM) with a 24-frame batch render in flight"
t=$(now)
timeout 60 podman "${PODMAN_FLAGS[@]}" stop -t 35 "$CTR" > "$OUT/stop.log" 2>&1 &
STOP_PID=$!
sleep 1
# draining: /v2/health/ready is 503 on a connection already open; uvicorn has closed its listener, so a new
# connection (this one) is refused: either way a load balancer stops sending (000 = refused)
READY_DRAINING=$(curl -s -o /dev/null -w '%{http_code}' --max-time 2 "$S/v2/health/ready" || true)
wait "$STOP_PID" || die "podman stop failed: $(cat "$OUT/stop.log")"
STOP_S=$(since "$t")
[ "$READY_DRAINING" != 200 ] || die "/v2/health/ready still 200 while draining"
wait "$BATCH_PID" || true
BATCH_CODE=$(cat "$OUT/batch.code")
BATCH_FRAMES=$(python3 -c '
import sys, zipfile
try:
    z = zipfile.ZipFile(sys.argv[1]); assert z.testzip() is None
    print(sum(n.startswith("frame_") for n in z.namelist()))
except Exception:
    print(0)' "$OUT/batch.zip")
EXIT_CODE=$(pm inspect --format '{{.State.ExitCode}}' "$CTR")
pm logs "$CTR" > "$OUT/container.log" 2>&1 || true
log "stopped in ${STOP_S} s, exit code $EXIT_CODE; in-flight batch: HTTP $BATCH_CODE, $BATCH_FRAMES frames"
[ "$EXIT_CODE" = 0 ] || die "exit code $EXIT_CODE after SIGTERM: $(tail -n 30 "$OUT/container.log")"
[ "$BATCH_CODE" = 200 ] && [ "$BATCH_FRAMES" = 24 ] || die "the in-flight batch did not finish (HTTP $BATCH_CODE)"
if grep -q 'Traceback' "$OUT/container.log"; then die "a traceback in the container log"; fi

python3 - << EOF
import json
mb = lambda b: None if b in (None, "null") else round(int(b) / 1e6, 1)
print(json.dumps({
    "image": "$IMAGE",
    "base": "$BASE",
    "base_kind": "$BASE_KIND",
    "podman": "$(podman --version | awk '{print $3}')",
    "oci_runtime": "$RUNTIME",
    "python": "$PYVER",
    "image_size_mb": mb("$IMAGE_BYTES"),
    "base_size_mb": mb("$BASE_BYTES"),
    "venv_mb": int("$VENV_MB"),
    "torch_in_image": False,
    "user_uid": int("$WHOAMI"),
    "model_dir": "$MODEL_DIR",
    "build_s": $BUILD_S,
    "cold_start_to_ready_s": $COLD_S,
    "healthcheck": "$HEALTH",
    "reconstruction_request_s": $RECON_WALL_S,
    "reconstruction_worker_s": $RECON_S,
    "gaussians": int("$GAUSS"),
    "render_first_s": $RENDER_S,
    "render_second_s": $RENDER2_S,
    "render_png": "$PNG",
    "stop_s": $STOP_S,
    "in_flight_batch_during_stop": {"http": int("$BATCH_CODE"), "frames": int("$BATCH_FRAMES")},
    "ready_while_draining": int("$READY_DRAINING"),
    "exit_code": int("$EXIT_CODE"),
    "host": {"cores": $(nproc), "loadavg_1m": float("$(cut -d' ' -f1 /proc/loadavg)")},
}, indent=1))
EOF
log "passed"
