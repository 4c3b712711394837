"""xyzcyl.common: what the runtime, the server and the HTTP client share, and nothing else of xyzcyl.

- ``wire``: the JSON bodies of the HTTP API (scene, list page, error, batch index, readiness) as pydantic models:
  the server's response models and what the client parses answers with;
- ``media``: the content sniffer (PNG, JPEG, EXR, TIFF by their magic bytes) and the one EXR writer;
- ``files``: atomic file and folder writes;
- ``progress``: the one place a tqdm bar is made (drawn only on a terminal);
- ``poses``: the camera-pose flags of `xyzcyl render` and `xyzcyl client render` (matrix parsing, camera moves).

The package imports nothing else from xyzcyl (tests/repo/test_layers.py checks it), and only what the client may use:
the standard library, numpy, pydantic, tqdm (and OpenImageIO inside the EXR writer), all in the base install, so
the ``client`` extra stays httpx alone."""
