"""Play a trajectory in its task and write what happened: PNG frames and an MP4, headless.

The MP4 is encoded with the ffmpeg binary that the `imageio-ffmpeg` wheel ships (H.264, yuv420p, so that
browsers and players open it); frames are written first, the video to a temporary file renamed at the end.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fluidlab_core.files import atomic_path


def task_for(traj, size: str | None = None, pressure: str | None = None):
    """The task a trajectory was written for, at the size and liquid pressure it records (or `size`, `pressure`)."""
    from fluidlab_core import tasks

    size = size or traj.metadata.get("size", "small")
    pressure = pressure or traj.metadata.get("pressure", "state")
    return tasks.make(traj.task, size=size, pressure=pressure)


def render_episode(traj, out_dir, every: int = 1, mp4: bool = True, size=(640, 480), progress=None,
                   task=None, fps: int | None = None) -> dict:
    """Step the task's reference physics with the trajectory, writing frame_XXXX.png every `every` steps
    (and the start) and episode.mp4 into `out_dir` (`fps` frames per second; default a quarter of real
    time). Returns {"frames": [...], "mp4": path or None, "loss"}."""
    task = task or task_for(traj)
    actions, position = task.actions_from_trajectory(traj)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sim = task.simulator()
    task.reset(sim, position)
    frames, images = [], []
    term_loss = task.loss(len(actions))
    total = 0.0

    def snap(k):
        title = f"{task.name} ({task.size}), {traj.method or 'trajectory'}: t = {k * task.dt:.3f} s"
        path = out / f"frame_{k:04d}.png"
        images.append(sim.render(path, view=task.camera, size=size, title=title))
        frames.append(str(path))

    snap(0)
    for k, tw in enumerate(task.twists(actions), start=1):
        total += sim.rollout(tw[None], term_loss, step_offset=k - 1, horizon=len(actions)).loss
        if k % every == 0 or k == len(actions):
            snap(k)
        if progress:
            progress(k, len(actions))
    fps = fps or max(1, round(1.0 / (task.dt * every) / 4))
    video = write_mp4(images, out / "episode.mp4", fps=fps) if mp4 else None
    return {"frames": frames, "mp4": video, "loss": total}


def write_mp4(images, path, fps: int = 10) -> str:
    """Encode (H, W, 3) uint8 images as an H.264 MP4 (atomically)."""
    import imageio_ffmpeg

    path = Path(path)
    h, w = images[0].shape[:2]
    h2, w2 = h - h % 2, w - w % 2  # yuv420p needs even sizes
    with atomic_path(path) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (w2, h2), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                             macro_block_size=1, ffmpeg_log_level="error")
        writer.send(None)
        try:
            for img in images:
                writer.send(np.ascontiguousarray(img[:h2, :w2, :3]))
        finally:
            writer.close()
    return str(path)
