#!/usr/bin/env bash
# Regenerate the committed Python modules of the SensorsimService protocol (server/sensorsim/*_pb2*.py) from
# server/sensorsim/{common,sensorsim}.proto (docs/simulators.md "The protocol"). Needs grpcio-tools
# (pip install grpcio-tools); run from anywhere. The .proto files are imported as xyzcyl/server/sensorsim/*.proto
# (protoc's VIRTUAL=DISK path mapping), so the generated modules import each other as xyzcyl.server.sensorsim.
# Keep grpcio and protobuf in pyproject's server extra at least at the versions this generator writes into the
# modules (grpc_tools.protoc --version; GRPC_GENERATED_VERSION in sensorsim_pb2_grpc.py).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python}
"$PY" -m grpc_tools.protoc -Ixyzcyl/server/sensorsim=server/sensorsim --python_out=. --pyi_out=. \
    --grpc_python_out=. xyzcyl/server/sensorsim/common.proto xyzcyl/server/sensorsim/sensorsim.proto
# protoc writes into ./xyzcyl/server/sensorsim/ (the import path); move the modules beside their .proto files
rm xyzcyl/server/sensorsim/common_pb2_grpc.py        # common.proto has no service
mv xyzcyl/server/sensorsim/*.py xyzcyl/server/sensorsim/*.pyi server/sensorsim/
rm -r xyzcyl
