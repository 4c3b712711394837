"""GET /v1/scenes/{id}/export?format=gltf|glb|spz|ply|splat (runtime.exports; usdz: tests/server/test_grpc.py):
streamed with Content-Length, an ETag naming the format (and the time), 304 for If-None-Match; 422 naming
``format`` or ``time``. On the session's reconstructed example rig (conftest ``env``)."""

from __future__ import annotations

import gzip
import json
import struct

from api_helpers import err, url


def test_each_format_downloads_with_its_length_type_and_etag(client, env):
    n = env.created.json()["gaussians"]
    # (gltf: the glb's JSON with the buffer inline, tests/runtime/test_exports.py; each format ~0.8 s here)
    for fmt, ctype in (("spz", "application/octet-stream"), ("glb", "model/gltf-binary"), ("ply", "application/x-ply"),
                       ("splat", "application/x-splat")):
        r = client.get(url(env, f"/export?format={fmt}"))
        assert r.status_code == 200, (fmt, r.text[:300])
        assert r.headers["content-type"] == ctype and int(r.headers["content-length"]) == len(r.content), fmt
        assert f'{env.sid}.{fmt}"' in r.headers["content-disposition"] and fmt in r.headers["etag"]
        again = client.get(url(env, f"/export?format={fmt}"), headers={"If-None-Match": r.headers["etag"]})
        assert again.status_code == 304 and again.content == b"", fmt
        if fmt == "spz":                    # gzip of the v3 header: magic, version, count
            assert struct.unpack_from("<III", gzip.decompress(r.content)) == (0x5053474E, 3, n)
        elif fmt == "glb":
            assert r.content[:4] == b"glTF" and struct.unpack_from("<I", r.content, 8)[0] == len(r.content)
            (size,) = struct.unpack_from("<I", r.content, 12)
            doc = json.loads(r.content[20:20 + size])
            assert doc["nodes"][0]["name"] == env.sid and doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
        elif fmt == "splat":
            assert len(r.content) == 32 * n
    timed = client.get(url(env, "/export?format=splat&time=12.5"))
    assert timed.status_code == 200 and timed.headers["etag"] != r.headers["etag"]     # a one-rig scene: same
    assert timed.content == r.content


def test_a_bad_format_or_time_is_a_422_naming_it(client, env):
    err(client.get(url(env, "/export?format=obj")), 422, "format")
    err(client.get(url(env, "/export?format=gltf&time=1&time=2")), 422, "time")
    err(client.get(url(env, "/export")), 422, "format")
    err(client.get(url(env, "/export?format=spz&time=inf")), 422, "time")
    err(client.get(url(env, "/export?format=spz&time=soon")), 422, "time")
    err(client.get(url(env, "/export?format=usdz&time=1")), 422, "time")
