"""``kpcn bench``'s report: ``accuracy_time.md`` (:func:`format_report`) and ``accuracy_time.png``
(:func:`plot_figure`) drawn from the record that :func:`kpcn_keras.studies.bench.bench` writes as
``accuracy_time.json``; no measuring here.
"""

from __future__ import annotations

import math

from kpcn_keras.studies.bench_stages import OURS
from prep.files import pyplot


def _f(value, fmt="{:.4f}") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if isinstance(value, float) and math.isinf(value):
        return "∞"
    return fmt.format(value)


def format_report(record: dict) -> str:
    cfg, m = record["config"], record["machine"]
    lines = [
        f"# What accuracy costs in time ({record['date']})",
        "",
        f"`{record['command'] or 'kpcn bench'}`, {record['started']} to {record['finished']}: "
        f"{len(record['scenes'])} held-out scenes ({', '.join(s['name'] for s in record['scenes'])}) rendered at "
        f"{', '.join(map(str, cfg['raw_spp']))} spp (raw Monte Carlo) and denoised at "
        f"{', '.join(map(str, cfg['input_spp']))} spp; every network trained for {cfg['budget']:g} s here.",
        "",
        f"Machine: {m['cpus']} CPUs, torch {m['torch']} on {m['torch_threads']} threads, numba on "
        f"{m['numba_threads']}; load average {m['load_average_before'][0]:.2f} before and "
        f"{m['load_average_after'][0]:.2f} after. Busiest other processes before: "
        f"{'; '.join(m['busy_before']) or 'none'}; after: {'; '.join(m['busy_after']) or 'none'}.",
        "",
        "## Equal-error saving: the spp raw Monte Carlo needs to reach the denoised relMSE",
        "",
        "Per scene (log-log interpolation on the raw ladder, or the fit a/n + b outside it), the median over "
        "scenes; *time saving* is raw render time at that spp over render + denoise time.",
        "",
        "| method | input spp | median equal-error spp | samples saved | time saved | how (scenes) |",
        "|---|---|---|---|---|---|",
    ]
    for row in record["equal_error"]:
        hows = ", ".join(f"{k} {v}" for k, v in sorted(row["hows"].items()))
        lines.append(f"| {row['method']} | {row['spp']} | {_f(row['median_equal_spp'], '{:.0f}')} | "
                     f"{_f(row['median_spp_saving'], '{:.1f}×')} | {_f(row['median_time_saving'], '{:.1f}×')} | "
                     f"{hows} |")
    lines += [
        "",
        "## Error against time per frame",
        "",
        "Seconds per frame: render (at the input spp) + denoise, the mean over scenes; relMSE and relSE p99.9: the "
        "geometric mean over scenes (the arithmetic mean of relMSE is in the JSON); DSSIM: the mean.",
        "",
        "| method | spp | s / frame | denoise ms | relMSE | DSSIM | relSE p99.9 |",
        "|---|---|---|---|---|---|---|",
    ]
    for method in record["methods"]:
        for p in method["points"]:
            denoise = _f(1e3 * p["denoise_s"], "{:.0f}") if "denoise_s" in p else "—"
            lines.append(f"| {method['name']} | {p['spp']} | {p['seconds']:.3f} | {denoise} | {p['relmse']:.4f} | "
                         f"{p['dssim']:.4f} | {p['relse_p999']:.4f} |")
    lines += ["", "Methods:", ""]
    lines += [f"- **{mm['name']}**: {mm['what']}" + (f" ({mm['training_seconds']:.0f} s of training)"
                                                    if "training_seconds" in mm else "")
              for mm in record["methods"]]
    lines += [
        "",
        "## Training cost: held-out error against training time",
        "",
        "| preset | budget s | trained s | relMSE | DSSIM | relSE p99.9 |",
        "|---|---|---|---|---|---|",
    ]
    for row in record["training"]:
        lines.append(f"| {row['preset']} | {row['budget']:g} | {row['training_seconds']:.0f} | {row['relmse']:.4f} | "
                     f"{row['dssim']:.4f} | {row['relse_p999']:.4f} |")
    lines += ["", "## Stage costs", ""] + _stage_lines(record["stages"])
    return "\n".join(lines) + "\n"


def _stage_lines(st: dict) -> list[str]:
    f, tr, sr, inf = st["features"], st["train_step"], st["shard_read"], st["inference"]
    lines = [
        "| stage | measured | against | ratio |",
        "|---|---|---|---|",
        f"| render | {st['render']['samples_per_s'] / 1e6:.2f} Msamples/s | — | — |",
        f"| features, numba | {1e3 * f['numba_s']:.1f} ms | EXR decode {1e3 * f['exr_decode_s']:.1f} ms | "
        f"{f['numba_s'] / f['exr_decode_s']:.2f}× |",
        f"| features, float64 numpy reference | {1e3 * f['numpy_s']:.1f} ms | numba {1e3 * f['numba_s']:.1f} ms | "
        f"{f['numpy_s'] / f['numba_s']:.1f}× |",
        f"| reading a training batch | {1e3 * sr['batch_s']:.1f} ms | a training step {1e3 * sr['step_s']:.0f} ms | "
        f"{100 * sr['ratio']:.1f} % |",
        f"| a Keras training step | {1e3 * tr['keras_s']:.0f} ms | plain torch {1e3 * tr['torch_s']:.0f} ms | "
        f"{tr['ratio']:.2f}× |",
    ]
    for ka in st["kernel_application"]:
        lines.append(f"| kernel application k={ka['k']} | {1e3 * ka['seconds']:.1f} ms | bandwidth floor "
                     f"{1e3 * ka['floor_seconds']:.1f} ms | {ka['ratio']:.2f}× |")
    lg = inf["large"]
    for name, row in inf["configurations"].items():
        lines.append(f"| denoise a {inf['frame'][0]}×{inf['frame'][1]} frame, {name} | {row['frame_ms']:.0f} ms | "
                     f"OIDN {_f(row.get('oidn_frame_ms'), '{:.0f} ms')} | {_f(row.get('frame_ratio'), '{:.2f}×')} |")
        lines.append(f"| denoise a {lg['frame'][0]}×{lg['frame'][1]} frame, {name} | {row['large_s']:.2f} s | "
                     f"OIDN {_f(row.get('oidn_large_s'), '{:.2f} s')} | {_f(row.get('large_ratio'), '{:.2f}×')} |")
    lines += [
        "",
        f"Frames alternate between our denoiser and OIDN, best of {st.get('repeats', '?')} each. Denoiser start-up: "
        f"loading the run {inf['load_s']:.2f} s, warm-up {inf['warm_up_s']:.2f} s (paid once per process). "
        f"`kpcn denoise` of the {lg['frame'][0]}×{lg['frame'][1]} frame as a command ({OURS}, tiles of {lg['tile']} "
        f"pixels): {lg['wall_s']:.1f} s in all, start-up included (its one frame also pays the convolutions' "
        f"set-up at the tiles' sizes, which the best-of times above leave out), peak resident memory "
        f"{_f(lg['peak_rss_mb'], '{:.0f} MB')}; it printed: {' / '.join(lg['printed'])}",
        "",
    ]
    sl, sw = st["shard_layouts"], st["shard_write"]
    lines += [
        f"`kpcn shards` of this render set as a command ({sw['layout']} layout, {sw['workers']} worker processes, "
        f"{sw['patches']} patches in {sw['shards']} shards): {sw['seconds']:.2f} s, start-up included, "
        f"{sw['patches_per_s']:.0f} patches/s, {sw['bytes_per_patch'] / 2**20:.2f} MB per patch; the `sync` after "
        f"it (the bytes the system had yet to put on disk) took {sw['sync_s']:.2f} s more; the command used "
        f"{sw['cpu_s']:.1f} s of CPU; memory available before it "
        f"{_f(sw['memory_mb_before'].get('MemAvailable'), '{:.0f} MB')}, the bench's own resident size "
        f"{_f(sw['memory_mb_before'].get('VmRSS'), '{:.0f} MB')}. Command: `{sw['command']}`.",
        "",
        f"Shard layouts, side by side on {sl['patches']} patches ({sl['patch_size']}×{sl['patch_size']}); writing "
        f"includes the file's checksum; a batch is {sl['batch_size']} random patches; the shipped one is "
        f"**{sl['default']}**:",
        "",
        "| layout | write patches/s | MB per patch | read a batch | largest relative error |",
        "|---|---|---|---|---|",
    ]
    for name, lay in sl["layouts"].items():
        lines.append(f"| {name} | {lay['write_patches_per_s']:.0f} | {lay['bytes_per_patch'] / 2**20:.3f} | "
                     f"{1e3 * lay['read_batch_s']:.1f} ms | {lay['max_rel_error']:.1e} |")
    return lines


def plot_figure(record: dict):
    """Error against seconds per frame (log axes), one curve per method, for relMSE, DSSIM and relSE p99.9;
    and the presets' held-out relMSE against training seconds."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12, 10))
    panels = (("relmse", "relMSE (geometric mean over scenes)"), ("dssim", "DSSIM (mean over scenes)"),
              ("relse_p999", "relSE p99.9 (geometric mean over scenes)"))
    # fixed styles for the yardsticks, and a colour of its own for each network (tab20 has enough)
    fixed = {"raw Monte Carlo": dict(color="black", lw=2, marker="o"),
             "OIDN": dict(color="crimson", ls="--", marker="s"),
             "OIDN prefiltered": dict(color="crimson", ls=":", marker="D"),
             "NLM": dict(color="grey", ls="--", marker="s")}
    networks = [m["name"] for m in record["methods"] if m["name"] not in fixed]
    # tab10 without its red and grey (OIDN's and NLM's), then tab20's light shades
    colours = [plt.cm.tab10.colors[i] for i in (0, 1, 2, 4, 5, 6, 8, 9)] + list(plt.cm.tab20.colors[1::2])

    def colour(name):
        return colours[networks.index(name) % len(colours)] if name in networks else None
    for ax, (key, label) in zip(axes.ravel(), panels):
        for method in record["methods"]:
            xs = [p["seconds"] for p in method["points"]]
            ys = [p[key] for p in method["points"]]
            style = fixed.get(method["name"]) or dict(marker="^", color=colour(method["name"]))
            ax.plot(xs, ys, label=method["name"], markersize=4, alpha=0.85, **style)
            for p in method["points"] if method["kind"] != "raw" else method["points"][::2]:
                ax.annotate(str(p["spp"]), (p["seconds"], p[key]), fontsize=6, alpha=0.7)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds per frame: render + denoise (points: spp)")
        ax.set_ylabel(label)
    ax = axes[1, 1]
    for preset in dict.fromkeys(r["preset"] for r in record["training"]):
        rows = [r for r in record["training"] if r["preset"] == preset]
        ax.plot([r["training_seconds"] for r in rows], [r["relmse"] for r in rows], "o-", label=preset,
                color=colour(preset))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training seconds (this machine)")
    ax.set_ylabel("held-out relMSE (geometric mean)")
    ax.set_title("training cost of the presets", fontsize=9)
    ax.legend(fontsize=8)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.suptitle(f"{record['command'] or 'kpcn bench'} ({record['date']})", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=min(6, len(labels)), fontsize=8, frameon=False)
    return fig
