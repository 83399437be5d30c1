"""``kpcn view``'s server (kpcn_keras/viewer.py) under misuse, as a user's tools would misuse it: killed during a
stroke, it stops cleanly (0 after SIGTERM, 130 after Ctrl-C, never an abort); a client's mistake (a bad or
too large Content-Length, a slow or cut body, a hang-up) is answered in one line and logged in one line without
reading more than the rectangle needs; 200 connections at once are all answered."""

import http.client
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from helpers.commands import command_env
from helpers.tiny import random_aovs

from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.viewer import ViewSession, listen
from prep import exr
from prep.errors import KpcnError

H, W = 96, 96


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    path = tmp_path_factory.mktemp("view-clients") / "frame.exr"
    exr.write_aovs(path, random_aovs(H, W, seed=5))
    return path


def _stroke_loop(port: int, stop: threading.Event, answers: list) -> None:
    """POST whole-frame strokes to the viewer on ``port`` until ``stop`` (or the server goes away)."""
    body = np.full((H, W), 2.0, np.float32).tobytes()
    while not stop.is_set():
        try:
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
            conn.request("POST", f"/api/stroke?y0=0&y1={H}&x0=0&x1={W}", body)
            answers.append(conn.getresponse().status)
            conn.close()
        except OSError:
            return


def _as_a_terminal_starts() -> None:
    """SIGINT at its default in the viewer's process, as a terminal's Ctrl-C finds it: a test run started in the
    background by a shell without job control (a CI script's ``cmd &``) passes SIGINT on ignored, and the
    viewer, like any Python program, then keeps it ignored (what ``nohup`` and background jobs rely on)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 0), (signal.SIGINT, 130)])
def test_a_kill_during_strokes_stops_the_viewer_cleanly(frame, tiny_slope_module_run, tmp_path, sig, status):
    # a fresh interpreter: the abort came from its exit while a stroke's thread was inside torch
    proc = subprocess.Popen([sys.executable, "-m", "kpcn_keras.cli", "-q", "view", str(frame), "--run",
                             str(tiny_slope_module_run), "--port", "0"], cwd=tmp_path, env=command_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_as_a_terminal_starts)
    try:
        port = None
        for line in proc.stdout:
            if line.startswith("serving "):
                port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
                break
        assert port is not None, proc.stderr.read()
        stop, answers = threading.Event(), []
        clients = [threading.Thread(target=_stroke_loop, args=(port, stop, answers)) for _ in range(3)]
        for client in clients:
            client.start()
        time.sleep(2)
        assert answers and set(answers) == {200}, answers  # strokes were being painted when the signal came
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
        stop.set()
        for client in clients:
            client.join()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "terminate called" not in err and "Traceback" not in err, err[-2000:]
    assert proc.returncode == status, (proc.returncode, err[-2000:])


@pytest.fixture(scope="module")
def session(frame, tiny_slope_module_run):
    return ViewSession.open(frame, Run(tiny_slope_module_run), slope=2.0,
                            settings=InferenceSettings(precision="float32"), log=lambda message: None)


@pytest.fixture
def server(session):
    """A served session on a free port, its client errors logged to ``server.lines``, reading bodies for at most
    0.5 s."""
    httpd = listen(0)
    httpd.session, httpd.read_seconds, httpd.lines = session, 0.5, []
    httpd.log = httpd.lines.append
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield httpd
    httpd.shutdown()
    httpd.server_close()


def exchange(port: int, head: bytes, body: bytes = b"", *, close_after=False) -> tuple[bytes, float]:
    """What the server answers to ``head`` (the request line and headers, without the blank line) and ``body``
    sent on a raw socket, and the seconds until the answer was whole (the server closed the connection)."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        begin = time.monotonic()
        sock.sendall(head + b"\r\n\r\n" + body)
        if close_after:
            sock.shutdown(socket.SHUT_WR)
        answer = b""
        while chunk := sock.recv(1 << 16):
            answer += chunk
        return answer, time.monotonic() - begin


def status_line(answer: bytes) -> tuple[int, str]:
    """The status code and the one-line body of an answer."""
    head, _, body = answer.partition(b"\r\n\r\n")
    return int(head.split()[1]), body.decode(errors="replace")


STROKE = b"POST /api/stroke?y0=0&y1=2&x0=0&x1=2 HTTP/1.1\r\nHost: 127.0.0.1"  # 16 bytes of λ


def test_a_bad_content_length_is_answered_in_one_line_before_the_body_is_read(server):
    port = server.server_address[1]
    body = np.full(4, 2.0, np.float32).tobytes()
    cases = ((b"Content-Length: abc", body, 400, "abc"), (b"Content-Length: -1", body, 400, "-1"),
             (b"Transfer-Encoding: chunked", b"10\r\n" + body + b"\r\n0\r\n\r\n", 411, "Content-Length"),
             (b"Content-Length: 17", body + b"!", 413, "16"))
    for header, sent, status, needle in cases:
        answer, _ = exchange(port, STROKE + b"\r\n" + header, sent)
        code, message = status_line(answer)
        assert code == status and needle in message and "\n" not in message, (header, answer)
    # a body far larger than the rectangle takes is refused at once, from its Content-Length, unread
    answer, seconds = exchange(port, STROKE + b"\r\nContent-Length: 268435456", body)
    code, message = status_line(answer)
    assert code == 413 and "268435456" in message and "16" in message and seconds < 0.4, (answer, seconds)
    assert len(server.lines) == len(cases) + 1 and all("\n" not in line for line in server.lines), server.lines
    # the session took none of them; a right stroke still paints
    answer, _ = exchange(port, STROKE + b"\r\nContent-Length: 16", body)
    assert status_line(answer)[0] == 200 and len(answer.partition(b"\r\n\r\n")[2]) == 2 * 2 * 3 * 4


def test_a_slow_or_cut_body_is_answered_within_the_servers_time(server):
    port = server.server_address[1]
    head = STROKE + b"\r\nContent-Length: 16"
    answer, seconds = exchange(port, head, b"\0\0\0@")  # 4 of 16 bytes, and the client waits
    code, message = status_line(answer)
    assert code == 408 and "4 of the body's 16 bytes" in message and 0.5 <= seconds < 3, (answer, seconds)
    answer, seconds = exchange(port, head, b"\0\0\0@", close_after=True)  # 4 of 16 bytes, and no more to come
    code, message = status_line(answer)
    assert code == 400 and "after 4 of its 16 bytes" in message and seconds < 0.4, (answer, seconds)


def test_a_client_that_hangs_up_early_is_logged_in_one_line_without_a_traceback(server, capfd):
    port = server.server_address[1]
    for _ in range(5):
        with socket.create_connection(("127.0.0.1", port)) as sock:
            sock.sendall(b"GET /api/view/input HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close with a reset
    deadline = time.monotonic() + 10
    while len(server.lines) < 5 and time.monotonic() < deadline:
        time.sleep(0.05)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Error" not in err, err
    assert server.lines and all("ended early" in line and "\n" not in line for line in server.lines), server.lines


def test_two_hundred_connections_at_once_are_all_answered_at_once(server):
    # connections beyond the listen queue are dropped, for the client's kernel to retry after 1 s, 3 s, 7 s… (or
    # reset): 33 s for these 200 with a queue of 5
    port, begin = server.server_address[1], time.monotonic()
    socks = [socket.create_connection(("127.0.0.1", port), timeout=30) for _ in range(200)]
    try:
        for sock in socks:
            sock.sendall(b"GET /api/info HTTP/1.0\r\n\r\n")
        answers = []
        for sock in socks:
            answer = b""
            while chunk := sock.recv(1 << 16):
                answer += chunk
            answers.append(status_line(answer)[0])
    finally:
        for sock in socks:
            sock.close()
    assert answers == [200] * 200 and time.monotonic() - begin < 10
    assert server.lines == []


def test_a_closed_session_paints_no_more(frame, tiny_slope_module_run):
    session = ViewSession.open(frame, Run(tiny_slope_module_run), slope=2.0, log=lambda message: None)
    before = session.view_bytes("denoised")
    assert session.close(timeout=1)
    with pytest.raises(KpcnError, match="stopping"):
        session.stroke((0, 2, 0, 2), np.full(4, 4.0, np.float32))
    assert session.view_bytes("denoised") == before
