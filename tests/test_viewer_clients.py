"""``kpcn view``'s server (kpcn_keras/viewer.py) under misuse, as a user's tools would misuse it: killed during a
stroke, it stops cleanly (0 after SIGTERM, 130 after Ctrl-C, never an abort); a client's mistake (a bad or
too large Content-Length, a slow or cut body, a hang-up) is answered in one line and logged in one line without
reading more than the rectangle needs; 200 connections at once are all answered."""

import http.client
import signal
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from helpers.commands import command_env
from helpers.tiny import random_aovs

from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.viewer import ViewSession, listen
from prep import exr

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


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 0), (signal.SIGINT, 130)])
def test_a_kill_during_strokes_stops_the_viewer_cleanly(frame, tiny_slope_module_run, tmp_path, sig, status):
    # a fresh interpreter: the abort came from its exit while a stroke's thread was inside torch
    proc = subprocess.Popen([sys.executable, "-m", "kpcn_keras.cli", "-q", "view", str(frame), "--run",
                             str(tiny_slope_module_run), "--port", "0"], cwd=tmp_path, env=command_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
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
