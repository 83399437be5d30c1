"""``kpcn view``: one frame on a local page, to compare the denoised result and paint λ where the artist wants it
(docs/denoise.md §7).

A :class:`ViewSession` reads the frame (any layout ``prep.layouts`` reads), the model that serves it
(``kpcn_keras.serving.Serving``), and what the page shows, once: the noisy ``input``, the ``denoised`` frame, the
``reference`` (``--reference``) and ``oidn`` (Intel Open Image Denoise on the same colour, with the albedo and
normal its renderer gives its own denoiser, when ``pyoidn`` is installed). For a run with a loss-specialisation
module (``--slope-module``) and no compositor it prepares the frame (``Denoiser.prepare``: each trunk run once) and
holds a λ map, uniform at first; a brush stroke is the map's new values in a rectangle, re-applied to that rectangle
alone (``PreparedFrame(map, region)``: the module is 1x1, so pixels outside a changed region keep their values
exactly). Any other run shows its denoised frame with the brush off and says why.

:func:`listen` and :func:`serve` answer on 127.0.0.1 only (``http.server``, the standard library; the page is
three files of ``kpcn_keras/view/``, nothing fetched from elsewhere, so it works offline):

- ``GET /``: the page (``index.html``, ``view.js``, ``view.css``);
- ``GET /api/info``: JSON: the frame's name and size, the views (with why one is missing), the model, the brush
  (λ range and starting λ) or why there is none;
- ``GET /api/view/<name>``: a view's linear RGB, float32, little-endian, row-major (H, W, 3);
- ``POST /api/stroke?y0=&y1=&x0=&x1=``: the body is the map's new λ in that rectangle, float32 row-major; the
  answer is the rectangle's denoised RGB (as a view), the seconds it took in ``X-Seconds``;
- ``GET /api/map.png``: the map as a 16-bit greyscale PNG over the run's λ range (what ``kpcn denoise
  --slope-map`` reads back: ``slope_map.png_bytes``);
- with ``--pair`` (the frame's second render: the page shows the two halves' mean, ``batch.join_pair``):
  ``POST /api/adapt?seconds=`` (or ``steps=&seed=``) starts adapting the model to the two halves in the background
  (``kpcn_keras.view_adapt``; 202 and its status, 409 while one runs), ``GET /api/adapt`` is its status (state, step,
  loss, seconds, and once done what the guard decided), which the page polls; once done the ``adapted`` view is the
  mean denoised by the adapted model (``kpcn denoise A --pair B --adapt``'s output).

A request the session cannot take (a rectangle outside the frame, λ outside the run's range, a body of
the wrong length, a brush on a run without the module) is answered 400 or 409 with a one-line message; a
client's mistake in HTTP (a bad or missing Content-Length, a body longer than its rectangle takes, a slow body)
400, 411, 413 or 408, the body read only up to what the rectangle takes; each is one line on the console
(docs/robustness.md §7). :func:`serve` stops on SIGTERM or Ctrl-C once the stroke being painted has ended.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import socket
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np

from kpcn_keras import slope_map
from kpcn_keras.batch import ReadOptions, join_pair, read_frame, read_halves, read_reference
from kpcn_keras.config import VIEW_ADAPT_SECONDS, VIEW_HOST, VIEW_PORT
from kpcn_keras.denoise import Denoiser, check_region
from kpcn_keras.run import Run
from kpcn_keras.serving import Serving
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.view_adapt import Adaptation, settings_of
from prep import layouts
from prep.errors import KpcnError, OptionError

PAGE_DIR = Path(__file__).with_name("view")
PAGE_FILES = {"/": ("index.html", "text/html"), "/view.js": ("view.js", "text/javascript"),
              "/view.css": ("view.css", "text/css")}
VIEWS = ("input", "denoised", "adapted", "reference", "oidn")  # in the page's order ("adapted": with a pair alone)
STOP_SECONDS = 30.0  # how long a stop waits for the stroke being painted
DROP_SECONDS, DROP_BYTES = 1.0, 1 << 20  # how much of a refused body is read and dropped before closing
VIEW_LABELS = {"input": "noisy input", "denoised": "kpcn", "adapted": "kpcn adapted", "reference": "reference",
               "oidn": "OIDN"}


class ViewSession:
    """One frame, the denoiser that serves it and the views of the page; :meth:`stroke` paints λ (the module
    docstring). :meth:`open` reads them from files; ``slope`` is λ to start from, everywhere (default: the
    run's validation λ); ``log(message)`` tells the console what is being computed. ``halves``: the layers of the
    two renders ``frame`` is the mean of (``--pair``), which the page's adapt action adapts to
    (:attr:`adaptation`, ``kpcn_keras.view_adapt``; None without)."""

    def __init__(self, frame: layouts.Frame, denoiser: Denoiser, reference: np.ndarray | None = None, *,
                 slope: float | None = None, log=print, halves: tuple[dict, dict] | None = None):
        # the mode's run folder, and the mode: what the page's status line says serves it
        self.path, self.shape = frame.path, frame.size
        self.model = f"{denoiser.run.dir} ({denoiser.settings.quality} quality)"
        self.lock = threading.Lock()  # held while the map or the views change: a stroke, inside torch, holds it
        self.closed = False
        begin = time.perf_counter()
        record, run = denoiser.record, denoiser.run.dir
        if slope is not None and not record.model.slope_channel:
            raise OptionError("slope", f"is for a run trained with λ as an input; {run} takes none")
        slope = record.validation_slope if slope is None else slope
        record.check_slope(slope)
        self.slope_range = tuple(float(v) for v in record.train.slope_range) if slope is not None else None
        if slope is not None and not self.slope_range[0] <= slope <= self.slope_range[1]:
            raise OptionError("slope", f"must lie within the run's trained range {list(self.slope_range)}, got {slope}")
        self.slope = slope
        log(f"{frame.path.name}: {self.shape[1]}x{self.shape[0]}, {frame.layout} layout; model {run}")
        self.brush_note = None
        if not record.model.slope_module:
            self.brush_note = (f"{run} takes one λ for the whole frame (trained with --slope-input, not "
                               "--slope-module)" if slope is not None else f"{run} takes no λ (trained with "
                               "neither --slope-input nor --slope-module)")
        elif denoiser.compositor is not None:
            # the pyramid re-runs the whole network at every scale, so a new map would not be interactive
            self.brush_note = f"{run} has a multiscale compositor, which re-runs the whole network for a new map"
        self.prepared = None
        if self.brush_note is None:
            log("running each trunk once (the brush re-runs only what follows λ: the module and its kernels or blend)")
            self.prepared = denoiser.prepare(frame.layers)
            self.map = np.full(self.shape, slope, np.float32)
            denoised = self.prepared(self.map)["default"]
        else:
            log("denoising")
            denoised = denoiser(frame.served_layers(), slope=slope)["default"]
        self.views = {"input": frame.layers["default"], "denoised": denoised}
        self.missing = {}
        if reference is not None:
            self.views["reference"] = reference
        else:
            self.missing["reference"] = "no --reference given"
        from prep import baselines

        if baselines.oidn_available():
            log("Intel Open Image Denoise on the same colour, with the albedo and normal its renderer gives its own "
                "denoiser")
            self.views["oidn"] = baselines.oidn_denoise(baselines.oidn_inputs(frame))
        else:
            self.missing["oidn"] = "pyoidn is not installed (pip install '.[oidn]')"
        self.views = {name: np.ascontiguousarray(view, "<f4") for name, view in self.views.items()}
        self.adaptation = None if halves is None else Adaptation(denoiser, halves, frame.layers, slope=slope, log=log)
        log(f"ready in {time.perf_counter() - begin:.1f} s")

    @classmethod
    def open(cls, frame_path, run: Run, reference=None, *, reading: ReadOptions = ReadOptions(),
             slope: float | None = None, settings: InferenceSettings = InferenceSettings(), log=print) -> ViewSession:
        """The session of the frame in ``frame_path`` (read by ``reading``: its layout, found from its channels
        by default, and view layer), the model ``run``'s variant that serves it (``Serving.variant``), applied
        with ``settings``, and the ``reference`` EXR if given. With ``reading.pair`` the frame is the mean of the
        two halves (``batch.join_pair``, each its own variance) and the page can adapt to them."""
        halves = None
        if reading.pair is None:
            frame = read_frame(frame_path, reading)
        else:
            a, b = read_halves(frame_path, reading)
            frame, halves = join_pair(a, b, (frame_path, reading.pair)), (a.layers, b.layers)
        ref = None if reference is None else read_reference(reference, frame_path, frame.size, reading)
        return cls(frame, Serving(run, settings).denoiser(frame.inputs), ref, slope=slope, log=log, halves=halves)

    def info(self) -> dict:
        h, w = self.shape
        brush = None
        if self.prepared is not None:
            brush = {"range": list(self.slope_range), "slope": self.slope}
        adapted = self.adaptation is not None and self.adaptation.view_bytes() is not None
        views = [{"name": v, "label": VIEW_LABELS[v], "available": v in self.views or (v == "adapted" and adapted),
                  **({"missing": self.missing[v]} if v in self.missing else {})}
                 for v in VIEWS if v != "adapted" or self.adaptation is not None]
        for view in views:
            if view["name"] == "adapted" and not adapted:
                view["missing"] = "not adapted yet: press adapt"
        adapt = None if self.adaptation is None else {"seconds": VIEW_ADAPT_SECONDS}
        return {"name": self.path.name, "width": w, "height": h, "model": self.model, "views": views,
                "brush": brush, "brush_note": self.brush_note, "adapt": adapt,
                "adapt_note": None if adapt else "no --pair given: adapting needs a second render of the frame"}

    def view_bytes(self, name: str) -> bytes:
        if name not in VIEWS:
            raise OptionError("view", f"must be one of {', '.join(VIEWS)}, got {name!r}")
        if name == "adapted":
            data = self._adaptation().view_bytes()
            if data is None:
                raise KpcnError("view adapted is not available: not adapted yet (POST /api/adapt)")
            return data
        if name not in self.views:
            raise OptionError("view", f"{name} is not available: {self.missing[name]}")
        with self.lock:
            return self.views[name].tobytes()

    def stroke_region(self, region) -> tuple[int, int, int, int]:
        """``region`` as the (y0, y1, x0, x1) ints of a rectangle of the frame a stroke may paint: OptionError
        if it is not one, KpcnError if the run has no brush."""
        if self.prepared is None:
            raise KpcnError(f"no brush: {self.brush_note}")
        return check_region(region, self.shape)

    def stroke(self, region, values: np.ndarray) -> tuple[np.ndarray, float]:
        """Set the λ map to ``values`` (float32, the rectangle's size) in ``region`` (y0, y1, x0, x1) and
        re-apply it there: the rectangle's denoised RGB and the seconds it took. KpcnError once closed."""
        y0, y1, x0, x1 = self.stroke_region(region)
        values = np.asarray(values, np.float32)
        if values.size != (y1 - y0) * (x1 - x0):
            raise OptionError("stroke", f"has {values.size} λ values for a {x1 - x0}x{y1 - y0} rectangle")
        outside = slope_map.range_error(values, self.slope_range)
        if outside:
            raise OptionError("stroke", outside)
        with self.lock:
            if self.closed:
                raise KpcnError("the viewer is stopping: no more strokes")
            begin = time.perf_counter()
            self.map[y0:y1, x0:x1] = values.reshape(y1 - y0, x1 - x0)
            rgb = self.prepared(self.map, region=(y0, y1, x0, x1))["default"]
            self.views["denoised"][y0:y1, x0:x1] = rgb
            return np.ascontiguousarray(rgb, "<f4"), time.perf_counter() - begin

    def _adaptation(self) -> Adaptation:
        if self.adaptation is None:
            raise KpcnError("no adaptation: no --pair given (adapting needs a second render of the frame)")
        return self.adaptation

    def adapt(self, query: dict) -> dict:
        """Start adapting with the settings of ``query`` (``view_adapt.settings_of``): its status."""
        adaptation = self._adaptation()
        return adaptation.start(settings_of(query))

    def adapt_status(self) -> dict:
        return self._adaptation().status()

    def close(self, timeout: float) -> bool:
        """Take no more strokes or adaptations, once the stroke being painted and the adaptation running (if any)
        have ended: whether they ended within ``timeout`` seconds. An interpreter that exits while a thread is
        inside torch aborts ("terminate called without an active exception"), so a process exits only after this
        is True."""
        if self.adaptation is not None and not self.adaptation.stop(timeout):
            return False
        if not self.lock.acquire(timeout=timeout):
            return False
        self.closed = True
        self.lock.release()
        return True

    def map_png(self) -> bytes:
        if self.prepared is None:
            raise KpcnError(f"no λ map: {self.brush_note}")
        with self.lock:
            return slope_map.png_bytes(self.map, self.slope_range)


class _ClientError(Exception):
    """A request the server answers ``status`` with a one-line message: the client's mistake in HTTP itself."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


class _Handler(BaseHTTPRequestHandler):
    server: ViewServer
    unread = 0  # bytes of the request's body not read (yet)

    @property
    def session(self) -> ViewSession:
        return self.server.session

    def setup(self):
        self.timeout = self.server.read_seconds  # a request's line and headers too: a silent client lets go
        super().setup()

    def log_request(self, code="-", size="-"):
        pass  # quiet, the console is the user's: only client errors are told

    def log_message(self, format, *args):  # noqa: A002 (the base class's name)
        self.server.log(f"{self.address_string()}: {format % args}")

    def _send(self, status: int, body: bytes, content_type: str, **headers) -> None:
        self.connection.settimeout(self.timeout)
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for key, value in headers.items():
            self.send_header(key.replace("_", "-"), value)
        self.end_headers()
        self.wfile.write(body)

    def _fail(self, status: int, message: str) -> None:
        self.server.log(f"{self.address_string()}: {self.command} {self.path}: {status} {message}")
        self._send(status, message.encode(), "text/plain; charset=utf-8")
        if self.unread:
            self._drop_rest()

    def _drop_rest(self) -> None:
        """Read and drop what the client still sends of a body left unread (bounded), so that closing does not
        reset the connection before the client has read the answer."""
        try:
            self.connection.shutdown(socket.SHUT_WR)
            self.connection.settimeout(DROP_SECONDS)
            left = DROP_BYTES
            while left > 0 and (chunk := self.rfile.read1(min(left, 1 << 16))):
                left -= len(chunk)
        except OSError:
            pass

    def _answer(self, handle) -> None:
        try:
            handle()
        except _ClientError as exc:
            self._fail(exc.status, str(exc))
        except OptionError as exc:
            self._fail(HTTPStatus.BAD_REQUEST, str(exc))
        except KpcnError as exc:
            self._fail(HTTPStatus.CONFLICT, str(exc))

    def do_GET(self):  # noqa: N802 (http.server's name)
        path = urlsplit(self.path).path
        if path in PAGE_FILES:
            name, kind = PAGE_FILES[path]
            return self._send(HTTPStatus.OK, (PAGE_DIR / name).read_bytes(), f"{kind}; charset=utf-8")
        if path == "/api/info":
            return self._send(HTTPStatus.OK, json.dumps(self.session.info()).encode(), "application/json")
        if path.startswith("/api/view/"):
            return self._answer(lambda: self._send(HTTPStatus.OK, self.session.view_bytes(path[len("/api/view/"):]),
                                                   "application/octet-stream"))
        if path == "/api/adapt":
            return self._answer(lambda: self._json(HTTPStatus.OK, self.session.adapt_status()))
        if path == "/api/map.png":
            name = f"{self.session.path.stem}-lambda.png"
            return self._answer(lambda: self._send(HTTPStatus.OK, self.session.map_png(), "image/png",
                                                   Content_Disposition=f'attachment; filename="{name}"'))
        self._fail(HTTPStatus.NOT_FOUND, f"no such page: {path}")

    def _json(self, status: int, value: dict) -> None:
        self._send(status, json.dumps(value).encode(), "application/json")

    def do_POST(self):  # noqa: N802
        url = urlsplit(self.path)
        if url.path == "/api/adapt":
            return self._answer(lambda: self._adapt(parse_qs(url.query)))
        if url.path != "/api/stroke":
            self.unread = 1  # a body, if any, is not read: dropped after the answer
            return self._fail(HTTPStatus.NOT_FOUND, f"no such endpoint: {url.path}")
        self._answer(lambda: self._stroke(parse_qs(url.query)))

    def _adapt(self, query: dict) -> None:
        """Start an adaptation (its settings in the query; a body, which it takes none of, dropped after the
        answer)."""
        length = self.headers.get("Content-Length", "0").strip()
        self.unread = int(length) if length.isdigit() else 1
        self._json(HTTPStatus.ACCEPTED, self.session.adapt(query))
        if self.unread:
            self._drop_rest()

    def _stroke(self, query: dict) -> None:
        """Answer a stroke, its body read only once the rectangle says how many bytes it takes."""
        self.unread = self._content_length()
        try:
            region = self.session.stroke_region([query[k][0] for k in ("y0", "y1", "x0", "x1")])
        except KeyError as exc:
            raise OptionError("stroke", f"needs y0, y1, x0 and x1; {exc.args[0]} is missing") from None
        y0, y1, x0, x1 = region
        takes = 4 * (y1 - y0) * (x1 - x0)
        if self.unread > takes:
            raise _ClientError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                               f"stroke: a body of {self.unread} bytes for a {x1 - x0}x{y1 - y0} rectangle, which "
                               f"takes {takes} (one float32 λ a pixel)")
        body = self._read_body()
        if len(body) % 4:
            raise OptionError("stroke", f"body must be float32 λ values, got {len(body)} bytes")
        rgb, seconds = self.session.stroke(region, np.frombuffer(body, "<f4"))
        self._send(HTTPStatus.OK, rgb.tobytes(), "application/octet-stream", X_Seconds=f"{seconds:.6f}")

    def _content_length(self) -> int:
        value = self.headers.get("Content-Length")
        if value is None:
            raise _ClientError(HTTPStatus.LENGTH_REQUIRED, "stroke: needs a Content-Length (its body's bytes)")
        if not re.fullmatch(r"-?[0-9]+", value.strip()):
            raise _ClientError(HTTPStatus.BAD_REQUEST, f"Content-Length must be a whole number of bytes, got {value!r}")
        if int(value) < 0:
            raise _ClientError(HTTPStatus.BAD_REQUEST, f"Content-Length must be 0 or more, got {value.strip()}")
        return int(value)

    def _read_body(self) -> bytes:
        """The body's :attr:`unread` bytes, within the server's ``read_seconds`` for all of them."""
        length, limit = self.unread, self.server.read_seconds
        deadline, chunks = time.monotonic() + limit, []
        while self.unread:
            try:
                self.connection.settimeout(max(deadline - time.monotonic(), 1e-3))
                chunk = self.rfile.read1(self.unread)
            except TimeoutError:
                raise _ClientError(HTTPStatus.REQUEST_TIMEOUT, f"stroke: {length - self.unread} of the body's {length} "
                                   f"bytes came in {limit:g} s") from None
            if not chunk:
                got, self.unread = length - self.unread, 0  # the client closed its side: nothing more comes
                raise OptionError("stroke", f"body ended after {got} of its {length} bytes")
            chunks.append(chunk)
            self.unread -= len(chunk)
        return b"".join(chunks)


class ViewServer(ThreadingHTTPServer):
    """The page's HTTP server; :attr:`session` is what it serves (set once the frame is read), :attr:`log`
    tells the console of each client error in one line, :attr:`read_seconds` bounds a request's reading."""

    daemon_threads = True  # a browser's open connection does not hold up Ctrl-C
    request_queue_size = 1024  # many connections at once (a page's fetches, a script's) wait, not reset
    read_seconds = 5.0
    session: ViewSession | None = None

    def __init__(self, *args, log=print, **kwargs):
        self.log = log
        super().__init__(*args, **kwargs)

    def handle_error(self, request, client_address):
        """One line for a client that hung up or timed out (not the standard library's traceback)."""
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError)):
            self.log(f"{client_address[0]}: the connection ended early ({type(exc).__name__}: {exc})")
        else:
            super().handle_error(request, client_address)


def listen(port: int = VIEW_PORT) -> ViewServer:
    """A server bound to 127.0.0.1:``port`` (0: a free port; ``server_address`` says which), not yet serving,
    bound before the frame is read so that a taken port fails at once; OptionError naming the port if it is."""
    try:
        return ViewServer((VIEW_HOST, port), _Handler)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise OptionError("port", f"{port} on {VIEW_HOST} is in use: choose another (0 takes a free one)") from None
        raise KpcnError(f"cannot listen on {VIEW_HOST}:{port}: {exc.strerror}") from None


class _Terminated(Exception):
    """SIGTERM, raised in the main thread as Ctrl-C raises KeyboardInterrupt."""


def serve(httpd: ViewServer, session: ViewSession, log=print) -> int:
    """Serve ``session`` on ``httpd`` until SIGTERM (the exit status is 0) or Ctrl-C (130). A stroke being
    painted then ends first (at most :data:`STOP_SECONDS`, else the process exits at once, with the same
    status): an interpreter that exits while a thread is inside torch aborts. Served from the main thread (the
    command), the process then exits without the interpreter's finalisation, which can abort on torch's own
    worker threads that strokes left behind ("terminate called without an active exception")."""
    httpd.session, httpd.log = session, log
    main = threading.current_thread() is threading.main_thread()
    if main:
        signal.signal(signal.SIGTERM, _terminated)
    status = 0
    try:
        log(f"serving {session.path.name} at http://{VIEW_HOST}:{httpd.server_address[1]}/ (Ctrl-C stops)")
        httpd.serve_forever()
    except KeyboardInterrupt:
        status = 130
    except _Terminated:
        status = 0
    finally:
        if main:  # a second signal while a stroke ends: exit now, as the fallback below does
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda signum, frame: _exit_now(status))
        httpd.server_close()
        if not session.close(STOP_SECONDS):
            log(f"a stroke or the adaptation did not end within {STOP_SECONDS:g} s: exiting without it")
            _exit_now(status)
        log("stopped")
    if main:
        _exit_now(status)
    return status


def _terminated(signum, frame):
    raise _Terminated


def _exit_now(status: int) -> None:
    """Exit without the interpreter's finalisation, which aborts while a thread is inside torch."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


__all__ = ["VIEWS", "ViewServer", "ViewSession", "listen", "serve"]
