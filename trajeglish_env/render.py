"""Top-down pictures and animations of scenes, rollouts and running episodes (matplotlib, headless).

The map is drawn once per renderer; each frame only moves the agent boxes, so animations of a few
hundred frames take seconds. Works for logged scenes and for rollouts (pass ``xyh``/``valid``); an env's
episodes are drawn from the simulation's live arrays (:class:`EpisodeRenderer`, :class:`LiveRenderer`),
external agents red, NPCs by class, log-replayed agents grey, with a window for ``human`` rendering.
Traffic signals are lamps at their stop points, red / amber / green by their state at each frame's step.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402

from trajeglish_env.geometry import box_corners  # noqa: E402
from trajeglish_env.scenario import (  # noqa: E402
    LANE_KINDS,
    ROAD_EDGE_KINDS,
    AgentKind,
    MapKind,
    Scenario,
    SignalState,
)
from trajeglish_env.scenario_io import atomic_path  # noqa: E402

KIND_COLORS = {
    AgentKind.VEHICLE: (0.20, 0.45, 0.85),
    AgentKind.PEDESTRIAN: (0.95, 0.55, 0.10),
    AgentKind.CYCLIST: (0.20, 0.70, 0.30),
}
SDC_COLOR = (0.85, 0.10, 0.15)
REPLAY_COLOR = (0.55, 0.55, 0.55)  # agents replaying their log in an env or rollout
# traffic-signal lamps at their stop points, by SignalState (unknown: grey)
SIGNAL_COLORS = np.full((max(SignalState) + 1, 3), 0.6)
SIGNAL_COLORS[[SignalState.STOP, SignalState.ARROW_STOP, SignalState.FLASHING_STOP]] = (0.90, 0.05, 0.05)
SIGNAL_COLORS[[SignalState.CAUTION, SignalState.ARROW_CAUTION, SignalState.FLASHING_CAUTION]] = (
    1.0,
    0.75,
    0.0,
)
SIGNAL_COLORS[[SignalState.GO, SignalState.ARROW_GO]] = (0.05, 0.75, 0.15)
_YELLOW = {8, 9, 10, 11, 12}
_BROKEN = {5, 8, 9}


FOLLOW_RADIUS = 50.0  # m: the half-width of a view that follows the sdc
MAX_FITTED_RADIUS = 150.0  # m: beyond this half-width a view of the whole scene follows the sdc instead


@dataclass(frozen=True)
class RenderConfig:
    """Picture settings: size in pixels, the view (metres around its centre) and motion trails."""

    width_px: int = 720
    height_px: int = 720
    view_radius: float | None = None  # half-width of the view in metres; None: fit the agents (or follow
    # the sdc at FOLLOW_RADIUS when fitting them would need more than MAX_FITTED_RADIUS)
    follow_sdc: bool = False  # centre every frame on the sdc instead of a fixed view
    trail_steps: int = 10
    show_ids: bool = False
    title: bool = True
    legend: bool = False  # a key of the colours in the lower left corner


class SceneRenderer:
    """Draws one scene's map once and renders agent frames on top of it."""

    def __init__(
        self,
        scenario: Scenario,
        xyh: np.ndarray | None = None,
        valid: np.ndarray | None = None,
        colors: np.ndarray | None = None,
        config: RenderConfig = RenderConfig(),
    ):
        self.scenario = scenario
        self.xyh = scenario.xyh if xyh is None else np.asarray(xyh, dtype=np.float64)
        self.valid = scenario.valid if valid is None else np.asarray(valid, dtype=bool)
        if self.xyh.shape[:2] != self.valid.shape or self.xyh.shape[0] != scenario.num_agents:
            raise ValueError(
                f"render: xyh {self.xyh.shape} / valid {self.valid.shape} must be [N,T,3] / [N,T] "
                f"with N = {scenario.num_agents} agents"
            )
        if colors is None:
            colors = np.array([KIND_COLORS[AgentKind(k)] for k in scenario.kind]).reshape(-1, 3)
            colors[scenario.sdc] = SDC_COLOR
        self.colors = np.asarray(colors, dtype=np.float64)
        self.config = config
        dpi = 100
        self.fig = plt.figure(figsize=(config.width_px / dpi, config.height_px / dpi), dpi=dpi)
        self.ax = self.fig.add_axes((0, 0, 1, 1))
        self.fig.set_facecolor((0.86, 0.86, 0.86))  # the axes patch is hidden with the axis
        self.ax.set_aspect("equal")
        self.ax.axis("off")
        self._draw_map()
        self._boxes = PolyCollection([], zorder=5, linewidths=0.6, edgecolors="k")
        self.ax.add_collection(self._boxes)
        self._trails = LineCollection([], zorder=4, linewidths=1.0, alpha=0.6)
        self.ax.add_collection(self._trails)
        self._heading = LineCollection([], zorder=6, linewidths=0.8, colors="k")
        self.ax.add_collection(self._heading)
        font = float(np.clip(9.0 * min(config.width_px, config.height_px) / 480.0, 5.0, 11.0))
        self._text = self.ax.text(
            0.01,
            0.99,
            "",
            transform=self.ax.transAxes,
            va="top",
            fontsize=font,
            zorder=7,
            bbox={"facecolor": "white", "alpha": 0.65, "edgecolor": "none", "pad": 1.5},
        )
        self._labels: list[plt.Text] = []
        self._lamps = None
        if scenario.signal_state is not None and len(scenario.signal_lane_id):
            xy = scenario.signal_xy
            self._lamps = self.ax.scatter(xy[:, 0], xy[:, 1], s=22, zorder=3, edgecolors="k", linewidths=0.4)
        if config.legend:
            self._draw_legend(font)
        self.focus_order = np.array([scenario.sdc], dtype=np.int64)
        self._centre: np.ndarray | None = None
        # a scene wider than MAX_FITTED_RADIUS (a straight highway: cars a few pixels in a thin strip) is
        # followed around the sdc instead, unless a radius is asked for
        self._follow = config.follow_sdc or (
            config.view_radius is None and self._fitted_view()[1] > MAX_FITTED_RADIUS
        )
        self._set_view(scenario.current_index)

    def _draw_map(self) -> None:
        sc = self.scenario
        groups: dict[str, list[np.ndarray]] = {}
        styles = {
            "lane": dict(colors=(0.75, 0.75, 0.75), linewidths=0.6, linestyles=(0, (4, 4))),
            "white": dict(colors="white", linewidths=1.2),
            "white_broken": dict(colors="white", linewidths=1.0, linestyles=(0, (3, 3))),
            "yellow": dict(colors=(0.95, 0.80, 0.10), linewidths=1.2),
            "yellow_broken": dict(colors=(0.95, 0.80, 0.10), linewidths=1.0, linestyles=(0, (3, 3))),
            "edge": dict(colors=(0.15, 0.15, 0.15), linewidths=1.4),
            "crosswalk": dict(colors=(0.55, 0.55, 0.55), linewidths=1.0),
            "bump": dict(colors=(0.55, 0.35, 0.75), linewidths=1.0),
            "driveway": dict(colors=(0.65, 0.55, 0.45), linewidths=0.8),
        }
        stop_pts = []
        for k in range(sc.num_polylines):
            pts = sc.polyline(k)
            kind = int(sc.map_kind[k])
            if kind == MapKind.STOP_SIGN:
                stop_pts.append(pts[0])
                continue
            if len(pts) < 2:
                continue
            if kind in LANE_KINDS:
                key = "lane"
            elif kind in ROAD_EDGE_KINDS:
                key = "edge"
            elif kind == MapKind.CROSSWALK:
                key = "crosswalk"
            elif kind == MapKind.SPEED_BUMP:
                key = "bump"
            elif kind == MapKind.DRIVEWAY:
                key = "driveway"
            else:
                key = ("yellow" if kind in _YELLOW else "white") + ("_broken" if kind in _BROKEN else "")
            groups.setdefault(key, []).append(pts)
        for key, lines in groups.items():
            self.ax.add_collection(LineCollection(lines, zorder=2 if key != "lane" else 1, **styles[key]))
        self._stop_signs = bool(stop_pts)
        if stop_pts:
            p = np.array(stop_pts)
            # a dark-red octagon ringed in white: unlike a signal lamp (a round lamp ringed in black)
            self.ax.scatter(
                p[:, 0],
                p[:, 1],
                marker="8",
                s=34,
                c=[(0.6, 0.0, 0.0)],
                edgecolors="w",
                linewidths=1.0,
                zorder=3,
            )

    def _draw_legend(self, font: float) -> None:
        """A key of the colours this picture uses (agent roles and classes, signal lamps, stop signs)."""
        from matplotlib.lines import Line2D
        from matplotlib.patches import Patch

        used = {tuple(np.round(c, 3)) for c in self.colors}
        names = [
            (SDC_COLOR, "sdc / external"),
            (KIND_COLORS[AgentKind.VEHICLE], "vehicle"),
            (KIND_COLORS[AgentKind.PEDESTRIAN], "pedestrian"),
            (KIND_COLORS[AgentKind.CYCLIST], "cyclist"),
            (REPLAY_COLOR, "log replay"),
        ]
        handles: list = [
            Patch(facecolor=c, edgecolor="k", label=n) for c, n in names if tuple(np.round(c, 3)) in used
        ]
        if self._lamps is not None:
            handles.append(
                Line2D(
                    [],
                    [],
                    marker="o",
                    ls="",
                    mfc=SIGNAL_COLORS[SignalState.STOP],
                    mec="k",
                    label="signal (its state)",
                )
            )
        if self._stop_signs:
            handles.append(Line2D([], [], marker="8", ls="", mfc=(0.6, 0.0, 0.0), mec="w", label="stop sign"))
        self.ax.legend(handles=handles, loc="lower left", fontsize=font * 0.85, framealpha=0.75)

    def _fitted_view(self) -> tuple[np.ndarray, float]:
        """Centre and half-width (m) of the view that holds every agent over the whole scene."""
        pts = self.xyh[..., :2][self.valid]
        if len(pts) == 0:
            pts = self.scenario.map_points if len(self.scenario.map_points) else np.zeros((1, 2))
        lo, hi = pts.min(0), pts.max(0)
        return (lo + hi) / 2, max(float((hi - lo).max()) / 2 + 10.0, 20.0)

    def _set_view(self, step: int) -> None:
        cfg = self.config
        focus = self.focus_at(step) if self._follow else None
        if focus is not None:
            centre = self._centre = self.xyh[focus, step, :2].copy()
            r = cfg.view_radius or FOLLOW_RADIUS
        elif self._follow and self._centre is not None:  # a gap in the followed track: keep the view
            centre, r = self._centre, cfg.view_radius or FOLLOW_RADIUS
        else:
            centre, r = self._fitted_view()
            r = cfg.view_radius or r
        aspect = cfg.width_px / cfg.height_px  # r fits the shorter side: a tall picture keeps the width
        self.ax.set_xlim(centre[0] - r * max(aspect, 1.0), centre[0] + r * max(aspect, 1.0))
        self.ax.set_ylim(centre[1] - r * max(1.0 / aspect, 1.0), centre[1] + r * max(1.0 / aspect, 1.0))

    def focus_at(self, step: int) -> int | None:
        """The agent a following view centres on at ``step``: the first of :attr:`focus_order` present
        then (the sdc by default; an env's external agents in order, so the view moves on to the next
        when the first one's episode ends), None when none is."""
        present = self.focus_order[self.valid[self.focus_order, step]]
        return int(present[0]) if len(present) else None

    def frame(self, step: int, caption: str | None = None) -> np.ndarray:
        """Render the agents at ``step``; returns an ``[H,W,3]`` uint8 image."""
        t_max = self.xyh.shape[1]
        if not 0 <= step < t_max:
            raise IndexError(f"render: step {step} out of range for {t_max} steps")
        if self._follow:
            self._set_view(step)
        live = np.flatnonzero(self.valid[:, step])
        corners = box_corners(self.xyh[live, step], self.scenario.size[live])
        self._boxes.set_verts(list(corners))
        self._boxes.set_facecolor(self.colors[live])
        front = (corners[:, 0] + corners[:, 1]) / 2
        centre = self.xyh[live, step, :2]
        self._heading.set_segments(list(np.stack([centre, front], 1)))
        lo = max(0, step - self.config.trail_steps)
        trails = [self.xyh[i, lo : step + 1, :2][self.valid[i, lo : step + 1]] for i in live]
        self._trails.set_segments([t for t in trails if len(t) > 1])
        self._trails.set_color([self.colors[i] for i, t in zip(live, trails, strict=True) if len(t) > 1])
        if self._lamps is not None:  # each signal's state at this step (past the log: its last)
            states = self.scenario.signal_state[min(step, self.scenario.signal_state.shape[0] - 1)]
            self._lamps.set_facecolor(SIGNAL_COLORS[np.clip(states, 0, len(SIGNAL_COLORS) - 1)])
        for label in self._labels:
            label.remove()
        self._labels = []
        if self.config.show_ids:
            for i in live:
                x, y = self.xyh[i, step, :2]
                self._labels.append(self.ax.text(x, y, str(self.scenario.track_id[i]), fontsize=6, zorder=8))
        if self.config.title:
            t = (step - self.scenario.current_index) * self.scenario.dt
            shown = f"agents={len(live)} now of {len(self.xyh)}"  # present at this step, of every track
            head = f"{self.scenario.source}:{self.scenario.scenario_id}  t={t:+.1f}s  {shown}"
            self._text.set_text(head + (f"\n{caption}" if caption else ""))
        self.fig.canvas.draw()
        rgba = np.asarray(self.fig.canvas.buffer_rgba())
        return np.ascontiguousarray(rgba[..., :3])

    def close(self) -> None:
        plt.close(self.fig)


def render_image(scenario: Scenario, step: int | None = None, **kwargs: object) -> np.ndarray:
    """One ``[H,W,3]`` uint8 picture of ``scenario`` at ``step`` (default: its current index)."""
    renderer = SceneRenderer(scenario, **kwargs)  # type: ignore[arg-type]
    try:
        return renderer.frame(scenario.current_index if step is None else step)
    finally:
        renderer.close()


VIDEO_SUFFIXES = (".gif", ".mp4")
MAX_GIF_FPS = 50  # browsers play GIF frame delays under 20 ms at about 10 fps


def check_output(out: str | os.PathLike[str], suffixes: tuple[str, ...], fps: int = 10) -> Path:
    """``out`` as a path a picture or video can be written to, checked before any frame is drawn (or any
    rollout sampled): its suffix among ``suffixes``, not a folder, no file where its folder should be,
    and for an MP4 an ffmpeg to encode it (imageio-ffmpeg's or ``IMAGEIO_FFMPEG_EXE``)."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in suffixes:
        raise ValueError(f"{out}: expected a {', '.join(suffixes[:-1])} or {suffixes[-1]} output path")
    if out.is_dir():
        raise ValueError(f"{out}: is a folder; give a file name ending in {suffix}")
    blocked = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocked is not None:
        raise ValueError(f"{out}: cannot write there: {blocked} is a file, not a folder")
    if suffix == ".gif" and fps > MAX_GIF_FPS:
        raise ValueError(
            f"{out}: a GIF at {fps} fps has frame delays browsers play at about 10 fps; use fps <= "
            f"{MAX_GIF_FPS} or an .mp4"
        )
    if suffix == ".mp4":
        try:
            import imageio_ffmpeg

            imageio_ffmpeg.get_ffmpeg_exe()
        except (ImportError, RuntimeError) as err:
            raise ValueError(
                f"{out}: writing an MP4 needs ffmpeg, and none was found ({err}); install imageio-ffmpeg "
                "or ffmpeg, set IMAGEIO_FFMPEG_EXE to an ffmpeg binary, or write a .gif"
            ) from None
    return out


def write_video(frames: Iterable[np.ndarray], out: str | os.PathLike[str], fps: int = 10) -> Path:
    """Write frames to a GIF or MP4 (chosen by the suffix) atomically, one frame at a time: ``frames`` may
    be a generator, so an MP4 of any length takes the memory of a frame or two."""
    import imageio.v2 as imageio

    out = check_output(out, VIDEO_SUFFIXES, fps)
    with atomic_path(out) as tmp:
        if out.suffix.lower() == ".gif":
            writer = imageio.get_writer(tmp, format="GIF", duration=1000 / fps, loop=0)
        else:  # even sizes suffice for yuv420p: no resize
            writer = imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", macro_block_size=2)
        with writer:
            for f in frames:
                writer.append_data(f)
    return out


def save_render(
    scenario: Scenario,
    out: str | os.PathLike[str],
    xyh: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    config: RenderConfig = RenderConfig(),
    steps: range | None = None,
    fps: int = 10,
    png_step: int | None = None,
    caption: str | None = None,
) -> Path:
    """Render ``scenario`` (or a rollout of it) to a PNG picture at ``png_step`` (default: the current
    step), or a GIF/MP4 animation over ``steps``; ``caption``: a line under every frame's title."""
    out = check_output(out, (".png", *VIDEO_SUFFIXES), fps)
    renderer = SceneRenderer(scenario, xyh=xyh, valid=valid, colors=colors, config=config)
    try:
        if out.suffix.lower() == ".png":
            img = renderer.frame(scenario.current_index if png_step is None else png_step, caption)
            import imageio.v2 as imageio

            with atomic_path(out) as tmp:
                imageio.imwrite(tmp, img, format="PNG")
            return out
        frames = (renderer.frame(t, caption) for t in (steps or range(renderer.xyh.shape[1])))
        return write_video(frames, out, fps=fps)
    finally:
        renderer.close()


# ---------------------------------------------------------------------------------------------- episodes


def role_colors(scenario: Scenario, external: np.ndarray, npc: np.ndarray) -> np.ndarray:
    """``[N,3]`` RGB: external agents red, NPCs by class (vehicle blue, pedestrian orange, cyclist green),
    log-replayed agents grey."""
    by_kind = np.array([KIND_COLORS[AgentKind(k)] for k in range(len(AgentKind))])
    colors = by_kind[scenario.kind.astype(np.int64)]
    colors[~npc & ~external] = REPLAY_COLOR
    colors[external] = SDC_COLOR
    return colors


class EpisodeRenderer:
    """Renders frames of an episode from the simulation's live state arrays (no copies)."""

    def __init__(
        self,
        scenario: Scenario,
        xyh: np.ndarray,
        valid: np.ndarray,
        external: np.ndarray,
        npc: np.ndarray,
        size: int = 480,
        radius: float = 40.0,
        legend: bool = False,
    ):
        colors = role_colors(scenario, external, npc)
        config = RenderConfig(
            width_px=size, height_px=size, view_radius=radius, follow_sdc=True, legend=legend
        )
        self.renderer = SceneRenderer(scenario, xyh=xyh, valid=valid, colors=colors, config=config)
        # the view follows the external agents in order (the next one when an episode ends), else the sdc
        order = np.flatnonzero(external)
        self.renderer.focus_order = order if len(order) else np.array([scenario.sdc], dtype=np.int64)
        self.renderer._set_view(scenario.current_index)
        self._window = None

    def frame(self, step: int) -> np.ndarray:
        """``[H,W,3]`` uint8 picture of step ``step``."""
        return self.renderer.frame(step)

    def save(self, path: str | os.PathLike[str], steps: range, fps: int = 10) -> Path:
        """Write the frames of ``steps`` to a GIF or MP4 (chosen by the suffix), drawn as they are written."""
        return write_video((self.frame(t) for t in steps), path, fps=fps)

    def show(self, frame: np.ndarray) -> None:
        """Display a frame in a window (pygame; set SDL_VIDEODRIVER=dummy to run headless)."""
        import pygame

        if self._window is None:
            pygame.init()
            self._window = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
            pygame.display.set_caption("trajeglish_env")
            driver = pygame.display.get_driver()
            if driver in ("offscreen", "dummy") and not os.environ.get("SDL_VIDEODRIVER"):
                warnings.warn(
                    f"render_mode='human': no display was found (SDL's {driver!r} driver), so no window "
                    "shows; use render_mode='rgb_array' (or save_video) on a machine without a screen",
                    stacklevel=3,
                )
        pygame.event.pump()
        surface = pygame.surfarray.make_surface(np.ascontiguousarray(frame.transpose(1, 0, 2)))
        self._window.blit(surface, (0, 0))
        pygame.display.flip()

    def close(self) -> None:
        self.renderer.close()
        if self._window is not None:
            import pygame

            pygame.display.quit()
            self._window = None


class LiveRenderer:
    """The :class:`EpisodeRenderer` of whatever simulation runs in one env slot: made on first use, made
    anew for a new episode or when the engine grows its arrays (so it never draws from stale ones)."""

    def __init__(self, size: int, radius: float, legend: bool = False):
        self.size, self.radius, self.legend = size, radius, legend
        self._renderer: EpisodeRenderer | None = None
        self._source: tuple[object, np.ndarray] | None = None

    def of(self, sim: object) -> EpisodeRenderer:
        """The renderer of ``sim`` (a running ``Simulation``)."""
        xyh = sim.driver.xyh  # type: ignore[attr-defined]
        if (
            self._source is None
            or self._source[0] is not sim
            or not np.may_share_memory(self._source[1], xyh)
        ):
            self.close()
            self._renderer = EpisodeRenderer(
                sim.sc,  # type: ignore[attr-defined]
                xyh,
                sim.driver.valid,  # type: ignore[attr-defined]
                sim.external,  # type: ignore[attr-defined]
                sim.policy_driven,  # type: ignore[attr-defined]
                size=self.size,
                radius=self.radius,
                legend=self.legend,
            )
            self._source = (sim, xyh)
        assert self._renderer is not None
        return self._renderer

    def close(self) -> None:
        """Release the renderer and its window."""
        if self._renderer is not None:
            self._renderer.close()
        self._renderer, self._source = None, None
