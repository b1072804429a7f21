"""The viewer: a viser server showing runs side by side, one row a run, frame-synchronised.

Each row holds, left to right, the input video frame (when the run's reference came from a video), the
subject's masks over it (``recon/masks.mp4``, written by the video front end), the
reconstructed reference's Gaussians and the target's. Every object is placed upright (the run's up axis
is the viewer's +y) and turned so the principal plane of its own motion faces the default camera
(:func:`sync4d.view.data.place`), at a common size. Only the current frame of each object is sent to the
browser, decoded when it is first shown (a few frames are kept for scrubbing back), so a long or large
run starts as fast as a short one.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from sync4d.errors import ConfigError
from sync4d.view.data import (
    CachedFrames,
    Placement,
    RunData,
    SplatFrame,
    part_boxes,
    part_colors,
    place,
    splat_buffer,
)

if TYPE_CHECKING:
    from viser import PointCloudHandle

log = logging.getLogger(__name__)
PANEL_GAP = 1.3   # [viewer units] between panel centres; objects are scaled to radius 0.5
ROW_GAP = 1.5
PLACEMENT_PROBE = 5000  # Gaussians sampled to place an object


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of the viewer (the command line's options).

    Attributes:
        host: interface to serve on (127.0.0.1: this machine only).
        port: HTTP/websocket port.
        fps: playback rate [frames/s]; 0 = the first run's frame rate.
        cache_frames: decoded frames kept per object for scrubbing.
        particle_size: simulation point size [viewer units].
        play: start playing.
        max_gaussians: an object with more Gaussians shows a fixed random subset of this many (each frame is
            sent whole to the browser: 32 bytes a Gaussian, 12.8 MB a frame at 400,000).
        seed: of that subset.
    """

    host: str = "127.0.0.1"
    port: int = 8080
    fps: float = 0.0
    cache_frames: int = 32
    particle_size: float = 0.006
    play: bool = False
    max_gaussians: int = 400_000
    seed: int = 0

    def validate(self) -> None:
        if not 0 < self.port < 65536:
            raise ConfigError(f"--port {self.port}: choose a port in 1..65535")
        if self.fps < 0 or self.cache_frames < 1 or self.particle_size <= 0 or self.max_gaussians < 1:
            raise ConfigError("viewer: --fps must be >= 0, cache_frames, max_gaussians >= 1 and particle_size > 0")


@dataclass
class ObjectPanel:
    """One object of a row: its frames, placement and scene handles."""

    frames: CachedFrames
    placement: Placement
    num_frames: int
    subset: np.ndarray | None = None
    splats: Any = None
    boxes: list[Any] | None = None


class RunRow:
    """The scene nodes of one run: video, reference and target panels, particles, part boxes."""

    def __init__(self, server: Any, run: RunData, row: int, config: ViewerConfig) -> None:
        self.server, self.run, self.config = server, run, config
        y = -ROW_GAP * row
        columns = (["video"] if run.video is not None else []) + (["masks"] if run.masks is not None else []) \
            + (["reference"] if run.reference else []) + ["target"]
        offsets = {name: np.array([PANEL_GAP * k, y, 0.0]) for k, name in enumerate(columns)}
        self.panels: dict[str, ObjectPanel] = {}
        rng = np.random.default_rng(config.seed)
        for name, source in (("reference", run.reference), ("target", run.target)):
            if source is None:
                continue
            subset = np.sort(rng.choice(source.num, config.max_gaussians, replace=False)) \
                if source.num > config.max_gaussians else None
            # Placement needs the extent and the plane of motion: a few thousand Gaussians tell both.
            probe = np.sort(rng.choice(source.num, PLACEMENT_PROBE, replace=False)) \
                if source.num > PLACEMENT_PROBE else None
            self.panels[name] = ObjectPanel(CachedFrames(source, config.cache_frames),
                                            place(source.all_means(probe), offsets[name], up=run.up),
                                            source.num_frames, subset)
        prefix = f"/run{row}"
        for name, offset in offsets.items():
            server.scene.add_label(f"{prefix}/{name}_label", name, position=tuple(offset + [0.0, 0.6, 0.0]))
        middle = 0.5 * (offsets[columns[0]] + offsets[columns[-1]])
        server.scene.add_label(f"{prefix}/run_label", run.name, position=tuple(middle + [0.0, 0.72, 0.0]))
        self.video = self._add_image(f"{prefix}/video", run.video, offsets.get("video"))
        self.masks = self._add_image(f"{prefix}/masks", run.masks, offsets.get("masks"))
        self.particles: PointCloudHandle | None = None
        self.prefix = prefix

    def _add_image(self, name: str, frames: Any, offset: np.ndarray | None) -> Any:
        """An image panel showing frame 0 of ``frames`` (a :class:`VideoFrames`), or None without frames."""
        if frames is None or offset is None:
            return None
        h, w = frames(0).shape[:2]
        # viser lays image rows downwards (+y down, as a camera's image); a half turn about x puts the
        # frame's top up in this y-up scene.
        return self.server.scene.add_image(name, frames(0), render_width=w / max(h, w), render_height=h / max(h, w),
                                           position=tuple(offset), wxyz=(0.0, 1.0, 0.0, 0.0))

    def show(self, t: int, *, part_colours: bool, boxes: bool, particles: bool) -> None:
        """Send frame ``t`` (modulo each object's length) with the chosen overlays."""
        for name, panel in self.panels.items():
            frame = panel.frames(t % panel.num_frames)
            if panel.subset is not None:
                frame = subset_frame(frame, panel.subset)
            self._show_splats(name, panel, frame, part_colours)
            self._show_boxes(name, panel, frame, boxes)
        if self.video is not None and self.run.video is not None:
            self.video.image = self.run.video(t)
        if self.masks is not None and self.run.masks is not None:
            self.masks.image = self.run.masks(t)
        self._show_particles(t, particles)

    def _show_splats(self, name: str, panel: ObjectPanel, frame: SplatFrame, part_colours: bool) -> None:
        colors = part_colors(frame.parts) if part_colours and frame.parts is not None else frame.colors
        buffer = splat_buffer(panel.placement.points(frame.means), panel.placement.covariances(frame.covariances),
                              colors, frame.opacities)
        if panel.splats is None:
            n = len(buffer)
            panel.splats = self.server.scene.add_gaussian_splats(
                f"{self.prefix}/{name}", centers=np.zeros((n, 3)), covariances=np.tile(np.eye(3) * 1e-6, (n, 1, 1)),
                rgbs=np.zeros((n, 3)), opacities=np.zeros((n, 1)))
        panel.splats.buffer = buffer

    def _show_boxes(self, name: str, panel: ObjectPanel, frame: SplatFrame, visible: bool) -> None:
        if frame.parts is None:
            return
        num_parts = int(frame.parts.max()) + 1
        if panel.boxes is None:
            if not visible:
                return
            panel.boxes = [self.server.scene.add_box(
                f"{self.prefix}/{name}_box{b}", color=tuple(int(c) for c in (part_colors(np.array([b]))[0] * 255)),
                dimensions=(1e-3, 1e-3, 1e-3), wireframe=True) for b in range(num_parts)]
        centers, sizes = part_boxes(panel.placement.points(frame.means), frame.parts, num_parts)
        for b, box in enumerate(panel.boxes):
            box.visible = visible and bool(sizes[b].any())
            if box.visible:
                box.position, box.dimensions = tuple(centers[b]), tuple(np.maximum(sizes[b], 1e-3))

    def _show_particles(self, t: int, visible: bool) -> None:
        x, panel = self.run.particles, self.panels.get("target")
        if x is None or panel is None or (self.particles is None and not visible):
            return
        points = panel.placement.points(x[t % len(x)])
        if self.particles is None:
            parts = self.run.particle_parts
            colors = part_colors(parts) * 0.6 if parts is not None and len(parts) == x.shape[1] \
                else np.full((x.shape[1], 3), 0.2)
            # Drawn over the target's splats, darker, in the target's placement.
            self.particles = self.server.scene.add_point_cloud(
                f"{self.prefix}/particles", points.astype(np.float32), (colors * 255).astype(np.uint8),
                point_size=self.config.particle_size, point_shape="circle", precision="float32")
        self.particles.visible = visible
        if visible:
            self.particles.points = points.astype(np.float32)


def subset_frame(frame: SplatFrame, index: np.ndarray) -> SplatFrame:
    """The Gaussians ``index`` of a frame."""
    return SplatFrame(frame.means[index], frame.covariances[index], frame.colors[index], frame.opacities[index],
                      None if frame.parts is None else frame.parts[index])


class Viewer:
    """A viser server showing ``runs`` (one row each), with play/pause, a frame slider and overlay toggles."""

    def __init__(self, runs: list[RunData], config: ViewerConfig) -> None:
        import viser

        config.validate()
        if not runs:
            raise ConfigError("viewer: no run folders given")
        self.config, self.runs = config, runs
        self.num_frames = max(r.num_frames for r in runs)
        self.server = viser.ViserServer(host=config.host, port=config.port, label="sync4d", verbose=False)
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        self.server.gui.main_panel.dock_right()  # beside the scene, not over it
        self.server.scene.set_up_direction("+y")
        self.server.scene.world_axes.visible = False
        self.rows = [RunRow(self.server, run, k, config) for k, run in enumerate(runs)]
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._build_gui()
        width = PANEL_GAP * (max(len(row.panels) + (row.video is not None) + (row.masks is not None)
                                 for row in self.rows) - 1)
        height = ROW_GAP * (len(runs) - 1)
        centre = np.array([0.5 * width, -0.5 * height, 0.0])
        # viser's wide default field of view: about 2.4 units across the canvas per unit of distance.
        distance = 0.48 * max(width + 1.2, 1.6 * (height + 1.5)) + 0.3
        self.server.initial_camera.look_at = tuple(centre)
        self.server.initial_camera.position = tuple(centre + [0.0, 0.15 * distance, distance])
        self.show(0)

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    def _build_gui(self) -> None:
        gui = self.server.gui
        self.slider = gui.add_slider("Frame", min=0, max=max(self.num_frames - 1, 1), step=1, initial_value=0)
        self.playing = gui.add_checkbox("Play", initial_value=self.config.play)
        prev_button, next_button = gui.add_button("Previous frame"), gui.add_button("Next frame")
        fps = self.config.fps or self._run_fps()
        self.fps = gui.add_number("FPS", initial_value=float(fps), min=0.5, max=120.0, step=0.5)
        self.part_colours = gui.add_checkbox("Part colours", initial_value=False)
        self.boxes = gui.add_checkbox("Matched part boxes", initial_value=False)
        self.particles = gui.add_checkbox("Simulation particles", initial_value=False)
        gui.add_markdown("Rows: runs. Columns: input video | subject masks | reconstructed reference | target. "
                         "A target part and the reference part it was matched to share a colour.")
        self.slider.on_update(lambda _: self.show(int(self.slider.value)))
        for toggle in (self.part_colours, self.boxes, self.particles):
            toggle.on_update(lambda _: self.show(int(self.slider.value)))
        prev_button.on_click(lambda _: self.step(-1))
        next_button.on_click(lambda _: self.step(1))

    def _run_fps(self) -> float:
        fps = self.runs[0].target.fps
        return fps if fps is not None else 12.0

    def step(self, delta: int) -> None:
        """Move the slider by ``delta`` frames (wrapping); the slider's callback shows the frame."""
        # viser defines the value setter apart from its getter, which mypy reads as a read-only property.
        self.slider.value = (int(self.slider.value) + delta) % self.num_frames  # type: ignore[misc]

    def show(self, t: int) -> None:
        """Show frame ``t`` of every run (one batch of messages)."""
        with self._lock, self.server.atomic():
            for row in self.rows:
                row.show(t, part_colours=bool(self.part_colours.value), boxes=bool(self.boxes.value),
                         particles=bool(self.particles.value))

    def stop(self) -> None:
        """Make :meth:`serve_forever` return (from another thread)."""
        self._stop.set()

    def serve_forever(self) -> None:
        """Advance frames while "Play" is ticked; returns on KeyboardInterrupt or :meth:`stop`, stopping the server."""
        try:
            while not self._stop.is_set():
                started = time.perf_counter()
                if self.playing.value and self.num_frames > 1:
                    self.step(1)
                time.sleep(max(1.0 / max(float(self.fps.value), 0.5) - (time.perf_counter() - started), 0.005))
        except KeyboardInterrupt:
            pass
        finally:
            self.server.stop()
