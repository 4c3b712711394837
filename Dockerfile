# xyzcyl CPU inference service: `xyzcyl serve` (FastAPI + onnxruntime + numba), no torch. docs/docker.md.
#
#   docker build -t xyzcyl .                     # or: podman build --format docker -t xyzcyl .
#   docker run --rm -p 127.0.0.1:8000:8000 -v xyzcyl-data:/data xyzcyl
#
# PYTHON_IMAGE is the base of both stages: python:3.11-slim from a registry by default.
# scripts/docker-smoke.sh passes a locally made one (Debian bookworm's python3.11, debootstrapped) where no image
# registry is reachable; nothing below depends on which: the venv is made with `python3 -m venv` and every
# command runs from /opt/venv/bin.
ARG PYTHON_IMAGE=python:3.11-slim
# EXTRAS: the package's pip extras in the venv. `server` is the service; `server,batch` adds ray[data] for
# `xyzcyl batch` on a Ray cluster (deploy/rayjob.yaml runs this image as xyzcyl:batch):
#   docker build --build-arg EXTRAS=server,batch -t xyzcyl:batch .
ARG EXTRAS=server

# ---- build: a venv with the package and its server extra (fastapi, uvicorn, ...), plus any other extras named in
# EXTRAS; the train extra (torch) is not installed
FROM ${PYTHON_IMAGE} AS build
ARG EXTRAS
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY pyproject.toml README.md ./
# the `xyzcyl` console script (xyzcyl.cli) and `python -m xyzcyl`: the package's modules at the top
COPY cli.py __main__.py ./
COPY common ./common
COPY runtime ./runtime
COPY server ./server
COPY clients ./clients
COPY model_export ./model_export
COPY testing ./testing
# non-editable: the code lives in the venv's site-packages, the model is found through XYZCYL_MODEL
RUN pip install ".[${EXTRAS}]" \
 && if python -c 'import torch' 2>/dev/null; then echo 'torch must not be in the image' >&2; exit 1; fi \
 && find /opt/venv -name '__pycache__' -prune -exec rm -rf {} + \
 && python -m compileall -q /opt/venv/lib

# ---- the web viewer's browser modules (docs/viewer.md): three.js and Spark from the lockfile (npm ci; Debian's node
# and npm, only in this stage); the service keeps the files its page loads
FROM ${PYTHON_IMAGE} AS viewer
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends nodejs npm \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY package.json package-lock.json ./
RUN npm ci --omit=dev --no-audit --no-fund \
 && mkdir -p /opt/viewer/three/examples \
 && cp -r node_modules/three/build node_modules/three/LICENSE /opt/viewer/three/ \
 && cp -r node_modules/three/examples/jsm /opt/viewer/three/examples/ \
 && mkdir -p /opt/viewer/@sparkjsdev/spark \
 && cp -r node_modules/@sparkjsdev/spark/dist node_modules/@sparkjsdev/spark/LICENSE /opt/viewer/@sparkjsdev/spark/ \
 && find /opt/viewer -name '*.map' -delete

# ---- the service
FROM ${PYTHON_IMAGE}
LABEL org.opencontainers.image.title="xyzcyl" \
      org.opencontainers.image.description="XYZCylinder CPU inference service (xyzcyl serve), no torch" \
      org.opencontainers.image.licenses="Apache-2.0"
# libgomp1: numba's OpenMP threading layer. Without it (python:3.11-slim and a minbase Debian have none) numba falls
# back to its workqueue layer, which aborts the process when two threads run kernels at once: the service would
# render one request at a time and make a drive's keyframes one at a time (runtime.numba_cache.threadsafe)
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends libgomp1 \
 && apt-get clean \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/*.bin
RUN groupadd --gid 10001 xyzcyl \
 && useradd --uid 10001 --gid 10001 --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin xyzcyl \
 && mkdir -p /data/store /tmp/numba-cache \
 && chown -R 10001:10001 /data /tmp/numba-cache
COPY --from=build /opt/venv /opt/venv
COPY models/xyzcyl-cpu-v1 /opt/xyzcyl/models/xyzcyl-cpu-v1
COPY --from=viewer /opt/viewer /opt/xyzcyl/node_modules
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    XYZCYL_MODEL=/opt/xyzcyl/models/xyzcyl-cpu-v1 \
    XYZCYL_VIEWER_MODULES=/opt/xyzcyl/node_modules \
    XYZCYL_STORE=/data/store \
    NUMBA_CACHE_DIR=/tmp/numba-cache
# scenes (and their Gaussians) live on the volume; everything else in the image is read-only to the service
VOLUME /data
WORKDIR /data
USER 10001:10001
# Compile every numba kernel (cache=True) into NUMBA_CACHE_DIR now, through the same warm-up `xyzcyl serve` runs
# before it reports ready (runtime/warmup.py: pinhole and equirect renders, the encoders, a reconstruction with
# LiDAR and the detail layer): without it every start compiles them (~85 s on 2 cores). numba keys its cache
# by CPU model: on another CPU the serve warm-up compiles once more (per container; mount a volume on
# /tmp/numba-cache to keep it across restarts). The cache is left writable to every uid: numba refuses to import
# the kernels when NUMBA_CACHE_DIR is not writable, and a platform may run the image as another uid (OpenShift,
# `docker run --user`).
RUN python -m xyzcyl.runtime.warmup \
 && chmod -R a+rwX /tmp/numba-cache
EXPOSE 8000
# podman keeps HEALTHCHECK only with --format docker (the OCI image format has no such field)
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
  CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/v2/health/live', timeout=4).status != 200)"]
# SIGTERM drains: /v2/health/ready turns 503 at once, requests in flight finish (up to 30 s), then exit 0;
# give `docker stop` / `podman stop` more than that (-t 35; Kubernetes: terminationGracePeriodSeconds >= 35)
STOPSIGNAL SIGTERM
CMD ["xyzcyl", "serve", "--host", "0.0.0.0", "--port", "8000"]
