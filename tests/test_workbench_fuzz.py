"""The workbench's HTTP API fed random and mutated requests on every endpoint (Hypothesis, tests/fuzz_http.py):
the real node and HTTP server on an in-process bus. Each request is answered below 500 (a 4xx is JSON
{"error": reason}, no traceback) and the server answers a good request right after (bench/fuzz.py runs longer)."""

from __future__ import annotations

import json
import os

from fuzz_http import bad_request, check, send, workbench_server
from hypothesis import HealthCheck, given, settings

EXAMPLES = int(os.environ.get("CONSTRUCTAIDE_FUZZ_EXAMPLES", "60"))


def test_every_endpoint_refuses_bad_requests_with_a_json_4xx() -> None:
    with workbench_server() as (http, bodies, ann_ids):
        seen: set[str] = set()

        @settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))  # fmt: skip
        @given(bad_request(bodies, ann_ids))
        def feed(req: tuple) -> None:
            seen.add(req[0].split(" / ")[0])
            check(send(http, req), req[0])
            ok = http.get("/api/site")
            assert ok.status_code == 200 and ok.json()["photos"] == 6, f"after {req[0]}: {ok.text[:200]}"

        feed()
        assert len(seen) >= 10, seen  # most endpoints were reached


def test_the_fuzz_findings_stay_fixed() -> None:
    """What the fuzz run found (each was a 500 or a stored NaN): now 4xx with a reason."""
    from fuzz_http import BIG_BODY

    def err(resp, status: int) -> str:
        assert resp.status_code == status, resp.text[:300]
        return resp.json()["error"]

    with workbench_server() as (http, bodies, ann_ids):
        good = bodies["POST /api/annotations"][1]
        nan = json.dumps({**good, "polygon_px": [[1.0, float("nan")], [9.0, 1.0], [9.0, 9.0]]}, allow_nan=True)
        assert "NaN is not a JSON number" in err(http.post("/api/annotations", content=nan), 400)
        assert "photo_id must be a string" in err(http.post("/api/annotations", json={**good, "photo_id": {}}), 400)
        assert "list of [u, v]" in err(http.post("/api/annotations", json={**good, "polygon_px": [{"x": 1}]}), 400)
        assert "rgba" in err(http.post("/api/annotations", json={**bodies["POST /api/annotations"][0],
                                                                  "rgba": [300, 0, 0, 0]}), 400)  # fmt: skip
        assert "larger than the limit" in err(http.post("/api/pick", content=b"[" + b"1," * BIG_BODY + b"1]"), 413)
        assert "nested too deeply" in err(http.post("/api/pick", content=b"[" * 100_000), 400)
        huge = {**bodies["POST /api/pick"][0], "u": 10**30}
        assert "int64" in err(http.post("/api/pick", json=huge), 400)
        far = json.loads(json.dumps(bodies["POST /api/pick"][0]))
        far["world_from_camera"][3] = 1e300
        assert "rigid transform" in err(http.post("/api/pick", json=far), 400)
        solve = json.loads(json.dumps(bodies["POST /api/photos/{photo_id}/solve"][0]))
        solve["points"][0]["world"][0] = 1e300
        assert "absurd world points" in err(http.post("/api/photos/p1/solve", json=solve), 400)
        assert "finite number" in err(http.get("/api/pick", params={"photo_id": "p1", "u": "nan", "v": "3"}), 400)
        assert "int64" in err(http.get("/api/model/visible", params={"at_ns": str(10**40)}), 400)
        assert "at_ns must be an integer" in err(http.post("/api/photos/p2/peek", json={"at_ns": "soon"}), 400)
        assert http.get("/api/annotations", params={"photo_id": "p1"}).status_code == 200
