"""`kpcn figures`: what it writes, and what it never writes over."""

import os

from helpers import checksums, random_aovs

from kpcn_keras.cli import main
from kpcn_keras.run import Run
from prep import exr


def test_figures_never_write_over_a_file_they_read(tiny_run, tmp_path, capsys):
    exr.write_aovs(tmp_path / "x-00004spp.exr", random_aovs(16, 16))
    exr.write_aovs(tmp_path / "x-00064spp.exr", random_aovs(16, 16, variances=False))
    figures = Run(tiny_run).figures_dir
    figures.mkdir(exist_ok=True)
    kernels = figures / "kernels.png"
    os.link(tmp_path / "x-00004spp.exr", kernels)  # the kernel figure's file is the input under another name
    try:
        before = checksums(tmp_path)
        assert main(["-q", "figures", "--run", str(tiny_run), str(tmp_path / "x-00004spp.exr")]) == 2
        err = capsys.readouterr().err
        assert f"figure {kernels} is the input file {tmp_path}/x-00004spp.exr itself" in err, err
        assert checksums(tmp_path) == before and kernels.read_bytes() == (tmp_path / "x-00004spp.exr").read_bytes()
    finally:
        kernels.unlink()
