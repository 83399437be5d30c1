"""``kpcn bench render``: what the path tracer costs, written to ``reports/render.{md,json}``.

Per built-in family (``families``, by default every one; scene 0 of each, seed 0): samples per second of
the kernel specialised to the scene's effects and of the all-effects kernel on the same scene, timed
alternately in one process (best of ``repeats``), and the time the specialisation saves. Also a diffuse-only
variant of a Cornell box (every surface made Lambertian), where specialisation has the most to leave out, and
the Cornell family at the depth of the reference point the project compares with (paths of up to 12
vertices, Russian roulette after 5). Kernels are compiled before timing. The load average before and after
is recorded: the machine is shared, so compare the ratios, which are measured side by side.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

from kpcn_keras.studies.report import Report
from prep.bounds import REPEATS, bounded, check_fields
from prep.render.families import DEFAULT_FAMILIES, check_families, make_scene
from prep.render.frame import FRAME_SIDE, SPP, check_frame, render
from prep.render.scene import EFFECTS, Scene, lambert

# A production CPU path tracer on a machine like this one: a 256x256 Cornell box with paths of up to
# 12 vertices and Russian roulette after 5, at about 1.4 million samples per second. A figure quoted to the
# project, never measured here: the report says so beside the figures it measures.
ANCHOR_SAMPLES_PER_S = 1.4e6
ANCHOR_DEPTH = (12, 5)  # (max_depth, rr_depth)
REPORT = "render"  # render.json and render.md in the report folder


@dataclass
class RenderBenchConfig:
    families: tuple[str, ...] = bounded(DEFAULT_FAMILIES, distinct=True)  # scene 0 of each is timed
    width: int = bounded(256, FRAME_SIDE)
    height: int = bounded(256, FRAME_SIDE)
    spp: int = bounded(16, SPP)
    repeats: int = bounded(3, REPEATS)
    out_dir: str = "reports"

    def __post_init__(self):
        self.families = tuple(self.families) if not isinstance(self.families, str) else self.families
        check_families(self.families)
        check_fields(self)
        check_frame(self.width, self.height)


def lambert_only(scene: Scene) -> Scene:
    """``scene`` with every surface but the lights made Lambertian (its albedo, or grey), untextured."""
    def one(m):
        if m.kind == "emitter":
            return m
        return lambert(m.albedo if max(m.albedo) > 0 else (0.5, 0.5, 0.5))

    return dataclasses.replace(scene, name=f"{scene.name} (lambert only)",
                               materials={k: one(m) for k, m in scene.materials.items()})


def _best_seconds(scene: Scene, cfg: RenderBenchConfig, effects=None, **depth) -> float:
    best = float("inf")
    for _ in range(cfg.repeats):
        start = time.perf_counter()
        render(scene, cfg.spp, 1, cfg.width, cfg.height, effects=effects, **depth)
        best = min(best, time.perf_counter() - start)
    return best


def _compare(scene: Scene, cfg: RenderBenchConfig) -> dict:
    from prep.render.kernels import kernel_for

    samples = cfg.width * cfg.height * cfg.spp
    for effects in (scene.effects(), EFFECTS):  # compile (or load) both kernels before timing
        render(scene, 2, 0, 8, 8, effects=effects)
    spec = _best_seconds(scene, cfg, effects=scene.effects())
    full = _best_seconds(scene, cfg, effects=EFFECTS)
    return {"scene": scene.name, "effects": sorted(scene.effects()), "specialised_s": spec, "all_effects_s": full,
            "specialised_samples_per_s": samples / spec, "all_effects_samples_per_s": samples / full,
            "saving": 1.0 - spec / full, "same_kernel": kernel_for(scene.effects()) is kernel_for(EFFECTS)}


def bench_render(cfg: RenderBenchConfig, progress: bool = True) -> dict:
    """Run the benchmark; writes ``<out_dir>/render.json`` and ``render.md`` and returns the record."""
    from tqdm import tqdm

    report = Report(cfg.out_dir, REPORT, png=False)
    session = report.begin()
    scenes = [make_scene(f, 0, 0) for f in cfg.families] + [lambert_only(make_scene("cornell", 0, 0))]
    rows = [_compare(s, cfg) for s in tqdm(scenes, desc="bench render", unit="scene", disable=not progress)]
    cornell = make_scene("cornell", 0, 0)
    max_depth, rr_depth = ANCHOR_DEPTH
    render(cornell, 2, 0, 8, 8, effects=cornell.effects())
    anchor_s = _best_seconds(cornell, cfg, effects=cornell.effects(), max_depth=max_depth, rr_depth=rr_depth)
    record = {
        "config": dataclasses.asdict(cfg),
        "machine": session.machine(),
        "families": rows,
        "anchor": {"scene": cornell.name, "max_depth": max_depth, "rr_depth": rr_depth,
                   "samples_per_s": cfg.width * cfg.height * cfg.spp / anchor_s,
                   "reference_samples_per_s": ANCHOR_SAMPLES_PER_S},
    }
    return report.write(record, format_report(record))


def format_report(record: dict) -> str:
    cfg, anchor = record["config"], record["anchor"]
    lines = [
        "# Path tracer: samples per second, specialised and all-effects kernels",
        "",
        f"`kpcn bench render`: {cfg['width']}x{cfg['height']} at {cfg['spp']} spp, best of {cfg['repeats']}, "
        f"{record['machine']['cpus']} CPUs, load average {record['machine']['load_average_before'][0]:.2f} before "
        f"and {record['machine']['load_average_after'][0]:.2f} after.",
        "",
        "| scene | effects | specialised Msamples/s | all-effects Msamples/s | time saved |",
        "|---|---|---|---|---|",
    ]
    for row in record["families"]:
        saved = f"{100 * row['saving']:.0f} %"
        if set(row["effects"]) == set(EFFECTS) or row["same_kernel"]:
            saved += " (one kernel timed twice: noise)"
        lines.append(f"| {row['scene']} | {', '.join(row['effects'])} | {row['specialised_samples_per_s'] / 1e6:.2f} "
                     f"| {row['all_effects_samples_per_s'] / 1e6:.2f} | {saved} |")
    lines += [
        "",
        f"Reference point: {anchor['scene']} with paths of up to {anchor['max_depth']} vertices and Russian roulette "
        f"after {anchor['rr_depth']}: {anchor['samples_per_s'] / 1e6:.2f} Msamples/s, against about "
        f"{anchor['reference_samples_per_s'] / 1e6:.1f} Msamples/s quoted for a production CPU path tracer on a "
        "machine like this one (a figure given, not measured here).",
        "",
    ]
    return "\n".join(lines)
