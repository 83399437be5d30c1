"""The screenshot of ``kpcn view`` under reports/ (issue 24): the page served for a frame and a run, driven in
headless Chromium (``tests/helpers.py``'s ``headless_chromium``: Debian's chromium and chromium-driver, Selenium)
as a user drives it: one brush stroke at the top of the λ range across the middle of the frame (λ at the low
end elsewhere), then kpcn left of the swipe and the λ map right of it, the swipe at the frame's middle; the
page's own status line says what the stroke cost.

  .venv/bin/python scripts/view_screenshot.py --run runs/lambda-mixture --frame F.exr --reference R.exr
                                              [--out reports/view.png]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers import headless_chromium  # noqa: E402 (the tests' own launcher: one set of flags)

from kpcn_keras.viewer import ViewSession, listen  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--frame", required=True)
    parser.add_argument("--reference")
    parser.add_argument("--slope", type=float, help="λ everywhere before the stroke (default: the range's low end)")
    parser.add_argument("--out", default="reports/view.png")
    args = parser.parse_args()

    from selenium.webdriver.common.actions.action_builder import ActionBuilder
    from selenium.webdriver.support.ui import WebDriverWait

    from kpcn_keras.run import Run
    from prep.processes import keep_freed_memory

    keep_freed_memory()  # as kpcn view does (kpcn_keras.cli.main)
    low = Run(args.run).record().train.slope_range[0]
    session = ViewSession.open(args.frame, args.run, args.reference, slope=args.slope or low)
    httpd = listen(0)
    httpd.session = session
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        with tempfile.TemporaryDirectory() as profile, headless_chromium(Path(profile)) as driver:
            driver.get(f"http://127.0.0.1:{httpd.server_address[1]}/")
            WebDriverWait(driver, 120).until(lambda d: d.execute_script("return Boolean(window.kpcn && kpcn.ready)"))
            driver.find_element("css selector", "input[name=mode][value=paint]").click()
            driver.execute_script("for (const [id, v] of [['brush-radius', 30], ['brush-slope', 1]]) {"
                                  "const e = document.getElementById(id); e.value = v;"
                                  "e.dispatchEvent(new Event('input')); }")
            h, w = session.shape

            def screen(x, y):
                return [round(v) for v in driver.execute_script(
                    "const s = kpcn.state, r = document.getElementById('canvas').getBoundingClientRect();"
                    "return [r.left + s.ox + arguments[0] * s.zoom, r.top + s.oy + arguments[1] * s.zoom];", x, y)]

            builder = ActionBuilder(driver)
            builder.pointer_action.move_to_location(*screen(0.2 * w, 0.5 * h))
            builder.pointer_action.pointer_down()
            for t in range(1, 9):
                builder.pointer_action.move_to_location(*screen((0.2 + 0.6 * t / 8) * w, (0.5 - 0.15 * (t % 2)) * h))
            builder.pointer_action.pointer_up()
            builder.perform()
            WebDriverWait(driver, 120).until(lambda d: d.execute_script("return kpcn.state.strokes === 1 && "
                                                                        "!kpcn.busy()"))
            # kpcn left of the swipe, the λ map right of it, the swipe at the frame's middle; no brush circle
            driver.execute_script(
                "const set = (id, v, kind) => { const e = document.getElementById(id); e.value = v;"
                "e.dispatchEvent(new Event(kind)); };"
                "set('left', 'denoised', 'change'); set('right', 'lambda', 'change');"
                "const s = kpcn.state, c = document.getElementById('canvas');"
                "set('split', (s.ox + 0.5 * s.info.width * s.zoom) / c.width, 'input');"
                "s.mouse = null; draw();")
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(args.out)
            print(driver.find_element("id", "status").text)
            print(f"wrote {args.out}")
    finally:
        httpd.shutdown()
        httpd.server_close()


if __name__ == "__main__":
    main()
