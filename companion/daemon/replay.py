"""`companion replay FOLDER`: re-run the vision pipeline on a recorded flight (for tuning on real footage).

Input: a flight folder written by `companion run --record-frames` (``frames/`` with
``timestamps.txt``, ``trajectory.tum`` of the flight's fused estimate, ``config.toml`` copy), or any
folder with ``frames/`` and a ``--config``. The recorded trajectory provides the start pose and the
attitude/height the ground odometer needs at each frame (the tlog is not required).

Output (``FOLDER/replay`` or ``--out``): ``trajectory.tum`` (the replayed vision poses, TUM
``stamp x y z qx qy qz qw``, NED body), ``overlay.avi`` (frames with the rack model drawn at the
tracked pose and the tracker/odometer health), and ``replay.json`` (counts and the difference to the
recorded trajectory).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.daemon.flight import TumWriter, read_tum
from companion.daemon.pipeline import FrameInputs, VisionPipeline, rack_std_floor_from_config
from companion.errors import ConfigError, InputError
from companion.geometry import frames, se3

__all__ = ["replay_folder", "run_replay_cli"]


def _interp_pose(stamps: FloatArray, Ts: FloatArray, t: float) -> FloatArray:
    """Recorded pose nearest in time (position linearly interpolated) at `t`."""
    if stamps.size == 0:
        return np.eye(4)
    k = int(np.clip(np.searchsorted(stamps, t), 0, stamps.size - 1))
    T: FloatArray = np.array(Ts[k], dtype=np.float64)
    for i in range(3):
        T[i, 3] = float(np.interp(t, stamps, Ts[:, i, 3]))
    return T


def _pipe_polylines(model: Any) -> list[FloatArray]:
    """Sample points (N, 3) along the top line of every pipe (rack frame) for the overlay."""
    lines = []
    for pipe in model.pipes():
        start = np.asarray(pipe.start_m, dtype=np.float64)
        d = np.asarray(pipe.direction_unit, dtype=np.float64)
        s = np.linspace(0.0, float(pipe.length), 60)
        for side in (-1.0, 1.0):
            off = np.cross(d, [0.0, 0.0, 1.0])
            n = float(np.linalg.norm(off))
            off = off / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])
            lines.append(start[None, :] + s[:, None] * d[None, :] + side * float(pipe.radius) * off[None, :])
    return lines


def replay_folder(folder: Path, config: Any, out_dir: Path, overlay: bool = True) -> dict[str, Any]:
    """Replay `folder`'s frames through the configured trackers; returns the summary written to replay.json."""
    import cv2

    from drivers.camera import list_images, load_camera_model, read_timestamps

    frames_dir = folder / "frames"
    if not frames_dir.is_dir():
        raise InputError(f"{folder}: no frames/ folder (record with `companion run --record-frames`)")
    files = list_images(frames_dir)
    if not files:
        raise InputError(f"{frames_dir}: no images")
    ts_file = frames_dir / "timestamps.txt"
    stamps = read_timestamps(ts_file, files) if ts_file.is_file() else [float(k) / config.camera.fps
                                                                          for k in range(len(files))]
    rec_t, rec_T = (np.zeros(0), np.zeros((0, 4, 4)))
    if (folder / "trajectory.tum").is_file():
        rec_t, rec_T = read_tum(folder / "trajectory.tum")
    camera = load_camera_model(config.camera)
    rack_model = None
    if config.rack.model:
        from companion.vision.rack import RackModel

        rack_model = RackModel.load(config.rack.model)
    from companion.config import build_dataclass

    rack_cfg = ground_cfg = None
    if config.vision.source in ("rack", "auto"):
        from companion.vision.rack import RackTrackerConfig

        rack_cfg = build_dataclass(RackTrackerConfig, dict(config.vision.rack_tracker), "vision.rack_tracker")
    if config.vision.source in ("ground", "auto"):
        from companion.vision.ground import GroundOdometerConfig

        ground_cfg = build_dataclass(GroundOdometerConfig, dict(config.vision.ground_odometer),
                                     "vision.ground_odometer")
    T_ned_rack = config.rack.T_ned_rack
    T_body_cam = config.mount.T_body_cam
    T0 = _interp_pose(rec_t, rec_T, stamps[0])
    pipeline = VisionPipeline(source=config.vision.source, camera=camera, T_body_cam=T_body_cam,
                              T_ned_rack=T_ned_rack, rack_model=rack_model, rack_config=rack_cfg,
                              ground_config=ground_cfg, initial_T_ned_body=T0,
                              rack_std_floor=rack_std_floor_from_config(config.vision),
                              rack_along_pipe_std_m=config.vision.rack_along_pipe_std_m)
    model = pipeline.rack_tracker.model if pipeline.rack_tracker is not None else None
    lines = _pipe_polylines(model) if model is not None else []
    ground_z = float(dict(config.filter.params).get("ground_z_ned_m", 0.0))
    out_dir.mkdir(parents=True, exist_ok=True)
    tum = TumWriter(out_dir / "trajectory.tum")
    writer: Any = None
    n_rack = n_ground = 0
    diffs: list[float] = []
    try:
        for seq, (path, stamp) in enumerate(zip(files, stamps, strict=True)):
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"{path}: cannot read the image")
            T_rec = _interp_pose(rec_t, rec_T, stamp)
            roll, pitch, _ = (float(v) for v in frames.euler_zyx_from_rotation(T_rec[:3, :3]))
            height = ground_z - float(T_rec[2, 3]) - float(T_body_cam[2, 3])
            m = pipeline.measure(image, float(stamp), seq, FrameInputs(height_m=height, roll_rad=roll,
                                                                         pitch_rad=pitch))
            T_est = None
            if m.rack_ok and m.rack is not None:
                n_rack += 1
                T_est = frames.T_ned_body_from_T_rack_cam(m.rack.T_rack_cam, T_ned_rack, T_body_cam)
            elif m.ground_ok and m.ground is not None:
                n_ground += 1
                R = frames.rotation_from_euler_zyx(roll, pitch, float(m.ground.yaw_rad))
                T_est = se3.make(R, np.array([float(m.ground.x_m), float(m.ground.y_m), float(T_rec[2, 3])]))
            if T_est is not None:
                tum.write(float(stamp), T_est)
                if rec_t.size:
                    diffs.append(float(np.linalg.norm(T_est[:3, 3] - T_rec[:3, 3])))
            if overlay:
                vis = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
                vis = np.ascontiguousarray(vis)
                if m.rack is not None and lines:
                    T_cam_rack = se3.inverse(np.asarray(m.rack.T_rack_cam))
                    colour = (0, 220, 0) if m.rack_ok else (0, 0, 230)
                    for pts in lines:
                        uv = camera.project(se3.act(T_cam_rack, pts))
                        good = np.all(np.isfinite(uv), axis=1)
                        if good.sum() >= 2:
                            cv2.polylines(vis, [np.round(uv[good]).astype(np.int32)], False, colour, 1)
                text = f"t={stamp:.2f} rack={'ok' if m.rack_ok else '--'} ground={'ok' if m.ground_ok else '--'}"
                if m.ground is not None:
                    text += f" inl={int(getattr(m.ground, 'num_inliers', 0))}"
                cv2.putText(vis, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1)
                if writer is None:
                    h, w = vis.shape[:2]
                    fps = max(1.0, float(config.camera.fps))
                    writer = cv2.VideoWriter(str(out_dir / "overlay.avi"), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h))
                writer.write(vis)
    finally:
        tum.close()
        if writer is not None:
            writer.release()
    summary = {
        "folder": str(folder),
        "frames": len(files),
        "rack_ok": n_rack,
        "ground_ok": n_ground,
        "trajectory": str(out_dir / "trajectory.tum"),
        "overlay": str(out_dir / "overlay.avi") if overlay else None,
        "vs_recorded_rms_m": None if not diffs else round(math.sqrt(float(np.mean(np.square(diffs)))), 4),
    }
    (out_dir / "replay.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary


def run_replay_cli(folder: Path, config_path: Path | None, out_dir: Path | None, overlay: bool) -> int:
    """`companion replay FOLDER`: exit 0 when the replay ran, 2 on bad input."""
    from companion.config import load_config

    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    path = config_path or (folder / "config.toml")
    if path.is_file():
        config = load_config(path)
    else:
        from companion.data import data_path

        if config_path is not None:
            raise ConfigError(f"{config_path}: no such file")
        config = load_config(data_path("sim_default.toml"))
    summary = replay_folder(folder, config, out_dir or folder / "replay", overlay)
    print(f"replayed {summary['frames']} frames: rack ok {summary['rack_ok']}, ground ok {summary['ground_ok']}; "
          f"trajectory {summary['trajectory']}" + (f", overlay {summary['overlay']}" if summary["overlay"] else ""))
    return 0
