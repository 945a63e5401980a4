"""The paper's image-degradation table (packet loss 1, 25, 50 % against PSNR),
measured over frames rendered by the camera module along the SAR route.

    python -m caviar_plugins.tools.results.degradation --protocol paper --out docs/results/paper-protocol \\
        [--runs runs/paper/sar-oracle runs/paper/sar-tree ...]

* ``paper``: the 2023 degradation, exactly ⌊N·p⌋ random bytes zeroed
  (:func:`caviar_plugins.protocol.zero_bytes`), frames along SAR rows 0-4 with the
  paper's persons. ``physical``: this project's image link, 1400-byte packets each
  lost with probability p, frames along the scene-frame route with the default targets.
* PSNR per frame against the undegraded frame (cv2.PSNR's definition, peak 255); the
  table gives the mean over frames and the PSNR of the pooled MSE. A frame that lost
  nothing (possible with packets) has infinite PSNR: it counts in the pooled MSE.
* With ``--runs``, the PSNR the image link recorded in those mission runs, per loss
  level, is added (frames in the loop, whatever throughput chose the level).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from caviar_plugins import protocol as paper
from caviar_plugins.assets import DATA
from caviar_plugins.mobility.frames import airsim_ned_to_scene
from caviar_plugins.mobility.waypoints import Path, read_waypoints
from caviar_plugins.vision.camera import VisualConfig, VisualScene
from caviar_plugins.vision.image_link import packet_loss

PAPER_PSNR = {0.01: 26.36, 0.25: 12.39, 0.50: 9.37}
"""The paper's table (dB); measured in 2023 on one AirSim image, 4-byte packets zeroed."""


def route_frames(protocol: str, count: int, seed: int = 1) -> list[np.ndarray]:
    if protocol == "paper":
        pts = airsim_ned_to_scene(read_waypoints(DATA / "central_park_path0.csv"))[: paper.PAPER_LAST_WAYPOINT + 1]
        cfg = VisualConfig(targets=[list(p) for p in paper.PAPER_PERSONS_SCENE])
    else:
        pts = read_waypoints(DATA / "central_park_path0_scene.csv")
        cfg = VisualConfig()
    route = Path(pts)
    scene = VisualScene(cfg, seed=seed)
    return [scene.render(route.at(s)) for s in np.linspace(0, route.length, count)]


def measure(frames: list[np.ndarray], protocol: str, rates=(0.01, 0.25, 0.5)) -> dict[float, dict]:
    rng = np.random.default_rng(1)
    out = {}
    for rate in rates:
        psnrs, mses = [], []
        for f in frames:
            if protocol == "paper":
                g = paper.zero_bytes(f, rate, rng)
            else:
                g = packet_loss(f, rate, rng, 1400)
            mse = float(np.mean((f.astype(float) - g.astype(float)) ** 2))
            mses.append(mse)
            psnrs.append(10 * np.log10(255**2 / mse) if mse > 0 else np.inf)
        finite = [p for p in psnrs if np.isfinite(p)]
        out[rate] = {"psnr_db_mean": float(np.mean(finite)) if finite else None,
                     "psnr_db_min": float(np.min(finite)) if finite else None,
                     "psnr_db_max": float(np.max(finite)) if finite else None,
                     "psnr_db_pooled": float(10 * np.log10(255**2 / np.mean(mses))),
                     "frames": len(frames), "frames_without_loss": int(sum(1 for m in mses if m == 0))}
    return out


def in_loop(runs) -> dict[float, dict]:
    import caviar
    from caviar_plugins.schema import IMAGE_QUALITY

    stats: dict[float, list[float]] = {}
    for r in runs:
        q = caviar.load_run(r).topic(IMAGE_QUALITY)
        for rate, value in zip(q["loss_rate"].to_list(), q["psnr_db"].to_list(), strict=True):
            stats.setdefault(round(float(rate), 4), []).append(float(value))
    return {k: {"psnr_db_mean": float(np.mean([v for v in vs if v < 99])) if any(v < 99 for v in vs) else None,
                "frames": len(vs)} for k, vs in sorted(stats.items())}


def write(result: dict, out: pathlib.Path, protocol: str, note: str = "") -> str:
    out.mkdir(parents=True, exist_ok=True)
    (out / "degradation.json").write_text(json.dumps(result, indent=2) + "\n")
    loop = result.get("in_loop", {})
    lines = ["| packet loss (%) | throughput (Mbit/s) | paper PSNR (dB) | ours: mean PSNR over frames (dB) | diff (dB) "
             "| ours: PSNR of pooled MSE (dB) | ours: in the mission loop (dB, frames) |",
             "|---:|---|---:|---:|---:|---:|---:|"]
    band = {0.01: "> 60", 0.25: "30-60", 0.5: "≤ 30"}
    rows = []
    for rate, m in result["offline"].items():
        rate = float(rate)
        p = PAPER_PSNR[rate]
        ours = m["psnr_db_mean"]
        lp = loop.get(str(rate)) or loop.get(rate)
        loop_txt = f"{lp['psnr_db_mean']:.2f} ({lp['frames']})" if lp and lp["psnr_db_mean"] is not None else "—"
        diff = f"{ours - p:+.2f}" if ours is not None else "—"
        ours_txt = f"{ours:.2f}" if ours is not None else "—"
        lines.append(f"| {100 * rate:g} | {band[rate]} | {p:.2f} | {ours_txt} | {diff} | {m['psnr_db_pooled']:.2f} "
                     f"| {loop_txt} |")
        rows.append((rate, p, ours))
    table = "\n".join(lines)
    (out / "degradation.md").write_text(f"# Image degradation ({protocol} protocol)\n\n{note}\n\n{table}\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    idx = np.arange(len(rows))
    ax.bar(idx - 0.2, [r[1] for r in rows], 0.4, label="paper")
    ax.bar(idx + 0.2, [r[2] if r[2] is not None else np.nan for r in rows], 0.4, label="ours (mean over frames)")
    ax.set(xticks=idx, xticklabels=[f"{100 * r[0]:g} %" for r in rows], xlabel="packet loss", ylabel="PSNR (dB)",
           title=f"Image degradation, paper vs ours ({protocol})")
    ax.grid(True, axis="y")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "degradation.png", dpi=100)
    plt.close(fig)
    return table


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m caviar_plugins.tools.results.degradation", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--protocol", choices=paper.PROTOCOLS, default="paper")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--runs", nargs="*", default=[])
    ap.add_argument("--out", type=pathlib.Path, required=True)
    args = ap.parse_args(argv)
    frames = route_frames(args.protocol, args.frames)
    result = {"protocol": args.protocol, "frames": args.frames,
              "frame_shape": list(frames[0].shape),
              "frame_rms": float(np.sqrt(np.mean(np.stack(frames).astype(float) ** 2))),
              "offline": {str(k): v for k, v in measure(frames, args.protocol).items()},
              "paper": {str(k): v for k, v in PAPER_PSNR.items()}}
    if args.runs:
        result["in_loop"] = {str(k): v for k, v in in_loop(args.runs).items()}
        result["runs"] = list(args.runs)
    how = ("bytes zeroed (2023 `applyFilter`)" if args.protocol == "paper"
           else "1400-byte packets zeroed (this project's image link)")
    note = (f"Measured by `python -m caviar_plugins.tools.results.degradation --protocol {args.protocol}` over "
            f"{args.frames} frames ({frames[0].shape[1]}×{frames[0].shape[0]}) rendered by the camera module "
            f"along the {'SAR route, rows 0-4' if args.protocol == 'paper' else 'scene-frame SAR route'}; loss: "
            f"{how}. Frame RMS {result['frame_rms']:.1f} (the paper's image: ≈ 122.6, which gives "
            f"PSNR = 6.364 − 10·log10 p). Frames that lost nothing (infinite PSNR, possible with packets: "
            f"{', '.join(str(m['frames_without_loss']) for m in result['offline'].values())} of {args.frames} at "
            f"1 / 25 / 50 %) are left out of the mean and kept in the pooled MSE. The in-loop column is the image "
            f"link's PSNR in the mission runs, by the loss level the throughput chose.")
    print(write(result, args.out, args.protocol, note))


if __name__ == "__main__":
    main()
