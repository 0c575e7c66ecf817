"""Pictures of a running episode: the map underneath, external agents, NPCs and log-replayed agents in
distinct colours, the view following the first external agent; GIF/MP4 of an episode; a window for the
``human`` render mode."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from trajeglish_env.render import KIND_COLORS, SDC_COLOR, RenderConfig, SceneRenderer, write_video
from trajeglish_env.scenario import AgentKind, Scenario

REPLAY_COLOR = (0.55, 0.55, 0.55)


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
    ):
        focus = int(np.flatnonzero(external)[0]) if external.any() else scenario.sdc
        colors = role_colors(scenario, external, npc)
        config = RenderConfig(width_px=size, height_px=size, view_radius=radius, follow_sdc=True)
        self.renderer = SceneRenderer(
            replace(scenario, sdc=focus), xyh=xyh, valid=valid, colors=colors, config=config
        )
        self._window = None

    def frame(self, step: int) -> np.ndarray:
        """``[H,W,3]`` uint8 picture of step ``step``."""
        return self.renderer.frame(step)

    def save(self, path: str | os.PathLike[str], steps: range, fps: int = 10) -> Path:
        """Write the frames of ``steps`` to a GIF or MP4 (chosen by the suffix)."""
        return write_video([self.frame(t) for t in steps], path, fps=fps)

    def show(self, frame: np.ndarray) -> None:
        """Display a frame in a window (pygame; set SDL_VIDEODRIVER=dummy to run headless)."""
        import pygame

        if self._window is None:
            pygame.init()
            self._window = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
            pygame.display.set_caption("trajeglish_env")
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

    def __init__(self, size: int, radius: float):
        self.size, self.radius = size, radius
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
                sim.npc,  # type: ignore[attr-defined]
                size=self.size,
                radius=self.radius,
            )
            self._source = (sim, xyh)
        assert self._renderer is not None
        return self._renderer

    def close(self) -> None:
        """Release the renderer and its window."""
        if self._renderer is not None:
            self._renderer.close()
        self._renderer, self._source = None, None
