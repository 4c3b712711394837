"""The gRPC SensorsimService (package ``nre.grpc.protos.sensorsim``) that NVIDIA's AlpaSim drives its renderer with
and CARLA's NuRec integration speaks, over the same scenes and renderer as the HTTP API (docs/simulators.md).

- ``common.proto``, ``sensorsim.proto``: the protocol, written for xyzcyl with the protocol's package, service,
  message and field names and numbers (the wire contract);
- ``common_pb2.py``, ``sensorsim_pb2.py``, ``sensorsim_pb2_grpc.py`` (+ ``.pyi``): generated from them by
  scripts/gen_sensorsim.sh and committed (never edited by hand);
- ``frames.py``: the messages to and from the runtime's terms (poses, the frame chain, cameras, lenses, sizes);
- ``servicer.py``: the grpc.aio servicer (app.py's lifespan starts it with ``grpc_port`` set).

Import the submodules by name: importing this package loads neither grpc nor protobuf."""
