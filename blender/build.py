"""Build the kpcn Blender add-on into the extension zip Blender 4.2+ installs (Install from Disk):
``dist/kpcn-blender-<version>.zip``, the manifest and the add-on's Python files at its root, the version read
from blender_manifest.toml. The standard library alone (``make addon``; the bpy wheel has no ``blender``
binary for ``blender --command extension build``). The same sources give the same bytes (fixed file times)."""

import argparse
import os
import re
import sys
import zipfile
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "kpcn_addon"
MANIFEST = "blender_manifest.toml"
FILE_TIME = (2024, 1, 1, 0, 0, 0)  # zip's earliest is 1980; any fixed time makes the archive reproducible


def manifest_version(source: Path = SOURCE) -> str:
    match = re.search(r'^version\s*=\s*"([^"]+)"', (source / MANIFEST).read_text(), re.M)
    if not match:
        raise SystemExit(f"{source / MANIFEST}: no version = \"...\" line")
    return match.group(1)


def build(out_dir: Path, source: Path = SOURCE) -> Path:
    """The zip written under ``out_dir`` (a temporary name, then renamed): its path."""
    files = sorted(p for p in source.iterdir() if p.name == MANIFEST or p.suffix == ".py")
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"kpcn-blender-{manifest_version(source)}.zip"
    tmp = out.with_name(f".{out.name}.tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for path in files:
            info = zipfile.ZipInfo(path.name, FILE_TIME)
            info.compress_type, info.external_attr = zipfile.ZIP_DEFLATED, 0o644 << 16
            z.writestr(info, path.read_bytes())
    os.replace(tmp, out)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="dist", help="folder the zip goes to (default: dist)")
    print(build(Path(ap.parse_args(argv).out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
