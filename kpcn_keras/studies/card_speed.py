"""The speed section of a shipped model's card measured again: ``make model-speed`` runs
``python -m kpcn_keras.studies.card_speed --model models/default --frame FRAME.exr``.

``kpcn ship`` times the model on a held-out frame of the run it ships (``kpcn_keras.card.speed``) and writes the
record beside the card as ``speed.json``; a shipped model keeps no renders, so timing it again takes a frame
(any layout ``kpcn denoise`` reads), wrapped around to 1920×1080 as the card's is. The record and the card's speed
section are written again from the measurement (``kpcn_keras.card.retime``), the rest of the card as it was.
Run it on an otherwise idle machine: it is a timing, kpcn beside OIDN (``pip install -e '.[oidn]'``).
"""

from __future__ import annotations

import argparse
import shlex
import sys

from kpcn_keras.card import retime
from kpcn_keras.run import Run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.card_speed", description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="models/default", help="the shipped model folder (default: models/default)")
    parser.add_argument("--frame", required=True, help="the EXR the timed 1920x1080 frame is made of")
    args = parser.parse_args(argv)
    command = shlex.join(["python", "-m", "kpcn_keras.studies.card_speed", *(sys.argv[1:] if argv is None else argv)])
    found = retime(Run(args.model), args.frame, command)
    oidn = "OIDN not installed" if found["oidn_s"] is None else f"OIDN {found['oidn_s']:.2f} s"
    print(f"{args.model}: kpcn {found['kpcn_s']:.2f} s, {oidn} on a {found['width']}x{found['height']} frame of "
          f"{args.frame}; wrote {args.model}/speed.json and its card's speed section")
    return 0


if __name__ == "__main__":
    sys.exit(main())
