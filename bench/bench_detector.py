"""Detector benchmark: RGB-D frames to constellations on this machine's CPU cores.

    python bench/bench_detector.py --out bench/results/detector.json

Renders a few frames of the synthetic office (640x480, the swarm's world, seed 0) as a
TUM RGB-D folder, then times, frame by frame over every frame ``--repeats`` times:

* baseline: decoding the frame's two PNGs (:func:`load_rgbd`), what any RGB-D
  detector pays before it sees a pixel;
* the model through :class:`OnnxDetector` (letterbox, onnxruntime, decode, NMS) with
  2 intra-op threads and with 1 (the service's default: it shares the robot's cores);
* object to point (:func:`object_points` on the frame's detections);
* the whole frame as the detector service does it (:func:`process_frame`: PNG decode,
  detect with 1 thread, points).

Each figure is a mean time per frame and a ratio against the decode baseline measured
in the same run; frames per second are 1 / mean time. The target is 30 frames per
second for the model at 640x480 on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints

from swarmrec.datasets.tum_rgbd import RgbdFrame, load_rgbd, read_tum_rgbd
from swarmrec.detection import CameraIntrinsics, DetectorSettings, OnnxDetector, RgbdPipeline, object_points
from swarmrec.detection.loader import DEFAULT_CONF_THRESHOLD
from swarmrec.models import DETECTOR_MODEL, shipped_model
from swarmrec.services.detector.rgbd import process_frame
from swarmrec.synthetic import OfficeConfig, generate_office
from swarmrec.synthetic.render import write_rgbd_sequence

TARGET_FPS = 30.0


def per_frame(frames: list[RgbdFrame], fn: Callable[[RgbdFrame], object], repeats: int) -> list[float]:
    """Seconds of ``fn`` on each frame, every frame ``repeats`` times (after one warm-up pass)."""
    for f in frames[:3]:
        fn(f)
    times = []
    for _ in range(repeats):
        for f in frames:
            t0 = time.perf_counter()
            fn(f)
            times.append(time.perf_counter() - t0)
    return times


def _detect_with(detector: OnnxDetector, images: dict[int, tuple[Any, Any]]) -> Callable[[RgbdFrame], object]:
    return lambda f: detector.detect(images[f.index][0])


def summary(times: list[float], baseline_s: float) -> dict[str, float]:
    mean = statistics.fmean(times)
    return {
        "mean_ms": 1e3 * mean,
        "p50_ms": 1e3 * float(np.percentile(times, 50)),
        "p90_ms": 1e3 * float(np.percentile(times, 90)),
        "fps": 1.0 / mean,
        "vs_decode_baseline": mean / baseline_s,
    }


def recommended_threshold(model: Path) -> float:
    try:
        value = json.loads((model.parent / "metrics.json").read_text())["recommended_conf_threshold"]
        return float(value)
    except (OSError, ValueError, KeyError, TypeError):
        return DEFAULT_CONF_THRESHOLD


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("bench/results/detector.json"))
    ap.add_argument("--model", type=Path, help="ONNX model (default: the project's detector)")
    ap.add_argument("--conf-threshold", type=float, help="default: the model's recommended one, else 0.25")
    ap.add_argument("--frames", type=int, default=40, help="frames rendered and timed (default 40)")
    ap.add_argument("--repeats", type=int, default=3, help="passes over the frames (default 3)")
    args = ap.parse_args()
    model = args.model or shipped_model(DETECTOR_MODEL)
    conf = args.conf_threshold if args.conf_threshold is not None else recommended_threshold(model)
    load_before = os.getloadavg()

    with tempfile.TemporaryDirectory(prefix="bench-detector-") as tmp:
        # Frames spread over the whole office path, so the timing sees near and far views.
        ds = generate_office(OfficeConfig(seed=0))
        step = len(ds.trajectory) // args.frames
        write_rgbd_sequence(ds, Path(tmp), frames=range(0, step * args.frames, step))
        frames = list(read_tum_rgbd(tmp).frames)
        images = {f.index: load_rgbd(f.rgb_path, f.depth_path) for f in frames}

        decode = per_frame(frames, lambda f: load_rgbd(f.rgb_path, f.depth_path), args.repeats)
        baseline_s = statistics.fmean(decode)
        detectors = {
            n: OnnxDetector(model, DetectorSettings(conf_threshold=conf, intra_op_threads=n)) for n in (2, 1)
        }
        detect = {n: per_frame(frames, _detect_with(d, images), args.repeats) for n, d in detectors.items()}
        boxes = {
            f.index: np.array([d.box for d in detectors[1].detect(images[f.index][0])]).reshape(-1, 4)
            for f in frames
        }
        camera = CameraIntrinsics()
        points = per_frame(
            frames, lambda f: object_points(images[f.index][1], boxes[f.index], camera), args.repeats
        )
        pipeline = RgbdPipeline(detectors[1], camera)
        whole = per_frame(frames, lambda f: process_frame(pipeline, f), args.repeats)
        n_boxes = [len(b) for b in boxes.values()]
        made = [process_frame(pipeline, f).constellation for f in frames]
        n_objects = [len(c) for c in made if c is not None]
        input_hw = detectors[1].input_hw

    result: dict[str, Any] = {
        "machine": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "onnxruntime": ort.__version__,
            "load_average_before": [round(v, 2) for v in load_before],
            "load_average_after": [round(v, 2) for v in os.getloadavg()],
        },
        "model": {"path": str(model), "input_hw": list(input_hw), "conf_threshold": conf},
        "frames": {
            "count": len(frames),
            "repeats": args.repeats,
            "size": "640x480",
            "boxes_per_frame": statistics.fmean(n_boxes),
            "objects_per_frame": statistics.fmean(n_objects),
        },
        "baseline_png_decode": summary(decode, baseline_s),
        "detect_2_threads": summary(detect[2], baseline_s),
        "detect_1_thread": summary(detect[1], baseline_s),
        "object_points": summary(points, baseline_s),
        "frame_pipeline_1_thread": summary(whole, baseline_s),
        "target_fps": TARGET_FPS,
        "note": (
            "mean time per 640x480 frame; vs_decode_baseline = mean / mean of decoding the frame's "
            "RGB and depth PNGs, measured in the same run; frame_pipeline = decode + detect + points "
            "as the detector service runs it"
        ),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    rows = [
        ("PNG decode of the frame pair (baseline)", "baseline_png_decode"),
        ("model, 2 intra-op threads", "detect_2_threads"),
        ("model, 1 thread", "detect_1_thread"),
        ("object to point", "object_points"),
        ("whole frame (decode + detect 1 thread + points)", "frame_pipeline_1_thread"),
    ]
    size = f"{input_hw[1]}x{input_hw[0]}"
    print(f"model {model} (input {size}, conf {conf:g}); {len(frames)} frames x {args.repeats} passes")
    print(f"{'':<50} {'ms/frame':>9} {'p90 ms':>8} {'fps':>8} {'x decode':>9}")
    for label, key in rows:
        r = result[key]
        ratio = r["vs_decode_baseline"]
        print(f"{label:<50} {r['mean_ms']:>9.2f} {r['p90_ms']:>8.2f} {r['fps']:>8.1f} {ratio:>9.2f}")
    verdict = "meets" if result["detect_2_threads"]["fps"] >= TARGET_FPS else "misses"
    print(f"target {TARGET_FPS:g} fps for the model on 2 threads: {verdict}; written to {args.out}")


if __name__ == "__main__":
    main()
