"""``kpcn view``'s server (kpcn_keras/viewer.py) over HTTP, without a browser: the views are the frame, the
reference and the run's own denoise; a stroke re-applies the λ map in its rectangle alone, equal to a full
denoise at the new map; the map comes back as the PNG ``kpcn denoise --slope-map`` reads; with a pair, the adapt
action runs in the background, its progress polled, and its view is ``kpcn denoise --pair --adapt``'s output;
requests it cannot take are refused in one line. The page in a real browser: ``test_viewer_browser.py``."""

import json
import socket
import threading
import urllib.error
import urllib.request
from contextlib import contextmanager

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.networks import randomise
from helpers.tiny import random_aovs

from kpcn_keras import slope_map
from kpcn_keras.batch import read_frame
from kpcn_keras.denoise import Denoiser
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.viewer import PAGE_DIR, VIEWS, ViewSession, listen
from prep import baselines, exr

H, W = 30, 44


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("view")
    aovs, ref = random_aovs(H, W, seed=11), random_aovs(H, W, seed=12, variances=False)
    exr.write_aovs(tmp / "frame.exr", aovs)
    exr.write_aovs(tmp / "reference.exr", ref)
    return tmp / "frame.exr", tmp / "reference.exr"


@contextmanager
def serving(session):
    httpd = listen(0)
    httpd.session = session
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


def get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=60) as res:
        return res.read()


def post(url: str, body: bytes) -> tuple[bytes, dict]:
    with urllib.request.urlopen(urllib.request.Request(url, data=body, method="POST"), timeout=60) as res:
        return res.read(), dict(res.headers)


def refused(call) -> tuple[int, str]:
    with pytest.raises(urllib.error.HTTPError) as info:
        call()
    return info.value.code, info.value.read().decode()


def rgb(data: bytes, h: int, w: int) -> np.ndarray:
    return np.frombuffer(data, "<f4").reshape(h, w, 3)


def quiet(message):
    pass


@pytest.fixture(scope="module")
def module_session(frame, tiny_slope_module_run):
    return ViewSession.open(frame[0], Run(tiny_slope_module_run), frame[1], slope=2.0,
                            settings=InferenceSettings(precision="float32"), log=quiet)


def test_the_page_shows_the_frame_the_reference_and_the_runs_own_denoise(frame, module_session,
                                                                         tiny_slope_module_run):
    with serving(module_session) as url:
        info = json.loads(get(f"{url}/api/info"))
        assert (info["width"], info["height"]) == (W, H)
        assert [v["name"] for v in info["views"]] == [v for v in VIEWS if v != "adapted"]  # no pair, no adapting
        assert info["adapt"] is None and "no --pair" in info["adapt_note"]
        assert {v["name"]: v["available"] for v in info["views"]}["oidn"] == baselines.oidn_available()
        assert info["brush"] == {"range": [1.0, 8.0], "slope": 2.0} and info["brush_note"] is None
        aovs, ref = exr.read_aovs(frame[0]), exr.read_aovs(frame[1], variances=False)
        np.testing.assert_array_equal(rgb(get(f"{url}/api/view/input"), H, W), aovs["default"])
        np.testing.assert_array_equal(rgb(get(f"{url}/api/view/reference"), H, W), ref["default"])
        den = Denoiser.from_run(Run(tiny_slope_module_run), InferenceSettings(precision="float32"))
        want = den(aovs, slope=2.0)["default"]
        np.testing.assert_allclose(rgb(get(f"{url}/api/view/denoised"), H, W), want, rtol=1e-5, atol=1e-6)
        page = get(f"{url}/").decode()
        assert "view.js" in page and "view.css" in page
        assert '<link rel="icon" href="data:,">' in page  # no request for /favicon.ico, which has no page
    for name in ("index.html", "view.js", "view.css"):  # offline: nothing is fetched from another host
        assert "://" not in (PAGE_DIR / name).read_text().replace("http://127.0.0.1", "")


@pytest.mark.parametrize("run", ["tiny_slope_module_run", "tiny_slope_mixture_run"])
def test_a_stroke_re_applies_its_rectangle_alone_as_a_full_denoise_at_the_new_map(frame, run, request):
    # weights far from the trained few steps' (whose zero-initialised head has barely moved), so that λ matters
    den = Denoiser.from_run(Run(request.getfixturevalue(run)), InferenceSettings(precision="float32"))
    for i, model in enumerate(den.networks.values()):
        randomise(model, seed=30 + i)
    session = ViewSession(read_frame(frame[0]), den, slope=2.0, log=quiet)
    aovs = exr.read_aovs(frame[0])
    y0, y1, x0, x1 = 5, 17, 20, 41
    painted = np.exp(np.random.default_rng(3).uniform(0, np.log(8), (y1 - y0, x1 - x0))).astype(np.float32)
    with serving(session) as url:
        before = rgb(get(f"{url}/api/view/denoised"), H, W).copy()
        body, headers = post(f"{url}/api/stroke?y0={y0}&y1={y1}&x0={x0}&x1={x1}", painted.tobytes())
        after = rgb(get(f"{url}/api/view/denoised"), H, W)
        png = get(f"{url}/api/map.png")
    assert float(headers["X-Seconds"]) > 0
    slopes = np.full((H, W), 2.0, np.float32)
    slopes[y0:y1, x0:x1] = painted
    want = den(aovs, slope=slopes)["default"]
    np.testing.assert_allclose(rgb(body, y1 - y0, x1 - x0), want[y0:y1, x0:x1], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(after[y0:y1, x0:x1], rgb(body, y1 - y0, x1 - x0))
    outside = np.ones((H, W), bool)
    outside[y0:y1, x0:x1] = False
    np.testing.assert_array_equal(after[outside], before[outside])
    assert np.abs(after[~outside] - before[~outside]).max() > 1e-4  # the module does read λ
    (frame[0].parent / "map.png").write_bytes(png)
    read_back = slope_map.read(frame[0].parent / "map.png", (H, W), (1.0, 8.0))
    np.testing.assert_allclose(np.log(read_back), np.log(slopes), atol=np.log(8) / 65535)


def test_requests_the_session_cannot_take_are_refused_in_one_line(module_session, frame, tiny_run):
    with serving(module_session) as url:
        before = get(f"{url}/api/view/denoised")
        cases = (
            ("y0=0&y1=4&x0=40&x1=50", np.full(40, 2.0), 400, ("inside the 44x30 frame", "(0, 4, 40, 50)")),
            ("y0=0&y1=2&x0=0&x1=2", np.full(4, 9.0), 400, ("[1, 8]", "9")),
            ("y0=0&y1=2&x0=0&x1=2", np.full(3, 2.0), 400, ("3 λ values", "2x2")),
            ("y0=0&y1=2&x0=0", np.full(4, 2.0), 400, ("x1 is missing",)),
        )
        for query, values, status, needles in cases:
            code, message = refused(lambda q=query, v=values: post(f"{url}/api/stroke?{q}",
                                                                    v.astype(np.float32).tobytes()))
            assert code == status and "\n" not in message
            for needle in needles:
                assert needle in message, (query, message)
        code, message = refused(lambda: get(f"{url}/api/view/albedo"))
        assert code == 400 and "input, denoised, adapted, reference, oidn" in message
        code, message = refused(lambda: post(f"{url}/api/adapt?seconds=5", b""))
        assert code == 409 and "no --pair given" in message
        code, message = refused(lambda: get(f"{url}/api/adapt"))
        assert code == 409 and "no --pair given" in message
        assert get(f"{url}/api/view/denoised") == before  # nothing applied
    plain = ViewSession.open(frame[0], Run(tiny_run), log=quiet)
    assert plain.info()["brush"] is None and "takes no λ" in plain.info()["brush_note"]
    with serving(plain) as url:
        code, message = refused(lambda: post(f"{url}/api/stroke?y0=0&y1=1&x0=0&x1=1", b"\0\0\0@"))
        assert code == 409 and "takes no λ" in message
        code, message = refused(lambda: get(f"{url}/api/view/reference"))
        assert code == 400 and "no --reference given" in message


def test_kpcn_view_refuses_a_taken_port_a_missing_frame_and_a_slope_the_run_cannot_take(frame, tmp_path,
                                                                                        tiny_slope_module_run,
                                                                                        tiny_run):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = run_main("view", frame[0], "--run", tiny_slope_module_run, "--port", port, cwd=tmp_path)
        assert_one_line_error(res, "--port", str(port), "in use")
    free = ("--port", "0")
    assert_one_line_error(run_main("view", "missing.exr", "--run", tiny_run, *free, cwd=tmp_path), "missing.exr")
    assert_one_line_error(run_main("view", frame[0], "--run", tiny_run, "--slope", "2", *free, cwd=tmp_path),
                          "--slope", "takes none")
    assert_one_line_error(run_main("view", frame[0], "--run", tiny_slope_module_run, "--slope", "20", *free,
                                   cwd=tmp_path), "--slope", "[1.0, 8.0]", "20")
    assert_one_line_error(run_main("view", frame[0], "--run", tiny_run, "--port", "70000", cwd=tmp_path), "--port")
    assert_one_line_error(run_main("view", frame[0], "--run", tiny_run, "--pair", frame[0], *free, cwd=tmp_path),
                          "--pair", "is the input", "itself")


# ---------------------------------------------------------------- the adapt action (kpcn view A --pair B)

PH, PW = 48, 64  # the guard's blocks of 16 pixels: three held out
STEPS = 20


@pytest.fixture(scope="module")
def halves_files(tmp_path_factory):
    from helpers.halves import write_halves

    return write_halves(tmp_path_factory.mktemp("view-halves"), PH, PW, seed=7)


def pair_session(halves_files, tiny_run):
    from kpcn_keras.batch import ReadOptions

    a, b = halves_files
    return ViewSession.open(a, Run(tiny_run), reading=ReadOptions(pair=b),
                            settings=InferenceSettings(precision="float32"), log=quiet)


def poll(url: str, seconds: float = 300.0) -> list[dict]:
    """GET /api/adapt until it is no longer running: every status seen."""
    import time

    seen, deadline = [], time.monotonic() + seconds
    while not seen or seen[-1]["state"] == "running":
        assert time.monotonic() < deadline, seen[-1]
        seen.append(json.loads(get(f"{url}/api/adapt")))
        time.sleep(0.05)
    return seen


def test_the_adapt_action_shows_what_kpcn_denoise_pair_adapt_writes_with_its_progress(halves_files, tiny_run,
                                                                                       tmp_path):
    from prep.inputs import mean_layers

    a, b = halves_files
    session = pair_session(halves_files, tiny_run)
    with serving(session) as url:
        info = json.loads(get(f"{url}/api/info"))
        views = {v["name"]: v for v in info["views"]}
        assert list(views) == list(VIEWS) and not views["adapted"]["available"]
        assert "press adapt" in views["adapted"]["missing"] and info["adapt"] == {"seconds": 30.0}
        code, message = refused(lambda: get(f"{url}/api/view/adapted"))
        assert code == 409 and "not adapted yet" in message
        assert json.loads(get(f"{url}/api/adapt"))["state"] == "idle"
        started = json.loads(post(f"{url}/api/adapt?steps={STEPS}&seed=3", b"")[0])
        assert started["state"] in ("running", "done") and started["steps"] == STEPS
        seen = poll(url)
        adapted = rgb(get(f"{url}/api/view/adapted"), PH, PW)
        denoised = rgb(get(f"{url}/api/view/denoised"), PH, PW)
        assert {v["name"]: v["available"] for v in json.loads(get(f"{url}/api/info"))["views"]}["adapted"]
    done = seen[-1]
    assert done["state"] == "done" and done["step"] == STEPS and np.isfinite(done["loss"]), done
    steps = [s["step"] for s in seen]
    assert steps == sorted(steps)  # progress only goes forward
    res = run_main("denoise", a, "--pair", b, "--adapt-steps", STEPS, "--adapt-seed", 3, "--run", tiny_run,
                   "--precision", "float32", "-o", tmp_path / "out.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    want = exr.read_aovs(tmp_path / "out.exr", variances=False)["default"]
    np.testing.assert_allclose(adapted, want, rtol=1e-5, atol=1e-6)
    outcome = done["outcome"]
    assert f"at steps {' and '.join(map(str, outcome['best_steps']))} of {STEPS}" in res.stdout
    assert outcome["line"].split(" in ")[0] in res.stdout
    ha, hb = exr.read_aovs(a), exr.read_aovs(b)
    plain = Denoiser.from_run(Run(tiny_run), InferenceSettings(precision="float32"))(mean_layers(ha, hb))["default"]
    np.testing.assert_allclose(denoised, plain, rtol=1e-5, atol=1e-6)  # kpcn's view: the halves' mean, as it is
    if outcome["kept"]:
        assert np.abs(adapted - denoised).max() > 1e-4
    else:
        np.testing.assert_allclose(adapted, denoised, rtol=1e-5, atol=1e-6)


def test_an_adaptation_refuses_a_second_one_and_bad_settings_and_stops_with_the_viewer(halves_files, tiny_run):
    session = pair_session(halves_files, tiny_run)
    with serving(session) as url:
        for query, words in (("seconds=soon", ("seconds must be a number", "'soon'")), ("seconds=-1", ("seconds",)),
                             ("speed=3", ("takes seconds, steps, seed", "speed")), ("seconds=nan", ("finite",))):
            code, message = refused(lambda q=query: post(f"{url}/api/adapt?{q}", b""))
            assert code == 400 and "\n" not in message and all(w in message for w in words), (query, message)
        assert json.loads(get(f"{url}/api/adapt"))["state"] == "idle"  # nothing started
        assert json.loads(post(f"{url}/api/adapt?steps=1000000", b"")[0])["state"] == "running"
        code, message = refused(lambda: post(f"{url}/api/adapt?seconds=5", b""))
        assert code == 409 and "an adaptation is running" in message
        assert session.close(60.0)  # the viewer stopping ends it at its next step
        status = json.loads(get(f"{url}/api/adapt"))
        assert status["state"] == "stopped" and 0 < status["step"] < 1000000, status
        code, message = refused(lambda: post(f"{url}/api/adapt?steps=5", b""))
        assert code == 409 and "stopping" in message
