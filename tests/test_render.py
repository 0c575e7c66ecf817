"""Top-down rendering of scenes to pictures and animations."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest

from trajeglish_env.render import (
    KIND_COLORS,
    SDC_COLOR,
    RenderConfig,
    SceneRenderer,
    render_image,
    save_render,
)
from trajeglish_env.scenario import AgentKind, Scenario


def _rgb(color: tuple[float, float, float]) -> np.ndarray:
    return (np.array(color) * 255).round()


def test_sdc_is_drawn_at_the_centre_when_followed(straight_scene: Scenario) -> None:
    img = render_image(
        straight_scene, config=RenderConfig(200, 160, view_radius=10.0, follow_sdc=True, title=False)
    )
    assert img.shape == (160, 200, 3) and img.dtype == np.uint8
    centre = img[80, 100 - 10].astype(
        float
    )  # slightly behind the centre: inside the box, off the heading tick
    assert np.abs(centre - _rgb(SDC_COLOR)).max() <= 3


def test_agents_get_kind_colours_and_rollouts_override_log(straight_scene: Scenario) -> None:
    xyh = straight_scene.xyh.copy()
    xyh[1, :, :2] = [100.0, -30.0]  # park the cyclist at a known place inside the view
    cfg = RenderConfig(200, 200, view_radius=50.0, title=False)
    r = SceneRenderer(straight_scene, xyh=xyh, config=cfg)
    try:
        img = r.frame(0)
    finally:
        r.close()
    # the fixed view is centred on the box around all valid positions; find the pixel of (100, -30)
    pts = xyh[..., :2][straight_scene.valid]
    centre = (pts.min(0) + pts.max(0)) / 2
    col = int(round((100.0 - (centre[0] - 50)) / 100 * 200))
    row = int(round(((centre[1] + 50) - (-30.0)) / 100 * 200))
    patch = img[row - 1 : row + 2, col - 3 : col].reshape(-1, 3).astype(float)
    assert (np.abs(patch - _rgb(KIND_COLORS[AgentKind.CYCLIST])).max(-1) <= 3).any()


def test_png_gif_and_mp4_outputs(tmp_path, straight_scene: Scenario) -> None:
    png = save_render(straight_scene, tmp_path / "scene.png", config=RenderConfig(160, 120))
    assert imageio.imread(png).shape[:2] == (120, 160)
    gif = save_render(
        straight_scene, tmp_path / "scene.gif", config=RenderConfig(96, 96), steps=range(0, 30, 3)
    )
    assert len(imageio.mimread(gif)) == 10
    mp4 = save_render(straight_scene, tmp_path / "scene.mp4", config=RenderConfig(96, 96), steps=range(5))
    assert mp4.stat().st_size > 1000
    with pytest.raises(ValueError, match=r"scene.bmp: expected a .png, .gif or .mp4"):
        save_render(straight_scene, tmp_path / "scene.bmp")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.gif", "scene.mp4", "scene.png"]


def test_wrong_rollout_shape_is_refused(straight_scene: Scenario) -> None:
    with pytest.raises(ValueError, match="with N = 6 agents"):
        SceneRenderer(straight_scene, xyh=np.zeros((5, 91, 3)), valid=np.ones((5, 91), bool))


def test_traffic_signals_are_lamps_coloured_by_each_frames_state(straight_scene: Scenario) -> None:
    import dataclasses

    from trajeglish_env.render import SIGNAL_COLORS
    from trajeglish_env.scenario import SignalState

    t = straight_scene.num_steps
    state = np.full((t, 1), SignalState.STOP, dtype=np.int8)
    state[20:] = SignalState.GO
    pts = straight_scene.xyh[..., :2][straight_scene.valid]
    lamp = np.array([[(pts[:, 0].min() + pts[:, 0].max()) / 2, 14.0]])  # mid-view, beside the road
    sc = dataclasses.replace(
        straight_scene, signal_lane_id=straight_scene.map_id[:1].copy(), signal_xy=lamp, signal_state=state
    )
    sc.validate()
    r = SceneRenderer(sc, config=RenderConfig(300, 300, view_radius=40.0, title=False))
    try:
        frames = {step: r.frame(step) for step in (5, 30)}
        x, y = r.ax.transData.transform(lamp[0])  # after a draw: the equal-aspect layout is settled
        row, col = int(round(300 - y)), int(round(x))
        colours = {
            step: img[row - 1 : row + 2, col - 1 : col + 2].reshape(-1, 3) for step, img in frames.items()
        }
        past_the_log = r.frame(t - 1)[row, col]
    finally:
        r.close()
    red, green = _rgb(SIGNAL_COLORS[SignalState.STOP]), _rgb(SIGNAL_COLORS[SignalState.GO])
    assert (np.abs(colours[5] - red).max(-1) <= 3).any() and not (
        np.abs(colours[5] - green).max(-1) <= 3
    ).any()
    assert (np.abs(colours[30] - green).max(-1) <= 3).any()
    assert np.abs(past_the_log - green).max() <= 3
    plain = SceneRenderer(straight_scene, config=RenderConfig(100, 100, title=False))
    assert plain._lamps is None
    plain.close()


def test_env_frames_draw_the_agents_a_policy_drives_by_class_and_the_log_grey() -> None:
    """README: external agents red, NPCs by class, log-replayed agents grey. Agents the log brings in
    later are the model's once they enter (TrajeglishNPC(drive_entering=True)); with npc="replay" every
    NPC is the log."""
    from helpers import bundle_scene, tiny

    from trajeglish_env.env import TrajeglishNPC, raw_env
    from trajeglish_env.render import REPLAY_COLOR, SDC_COLOR, role_colors

    scene = bundle_scene("highway-intersection-999001")  # four agents enter after the current step
    cur = scene.current_index
    entering = scene.valid[:, cur + 1 :].any(1) & ~scene.valid[:, cur]
    driven = {}
    for name, npc in (("model", TrajeglishNPC(tiny())), ("idm", "idm"), ("replay", "replay")):
        env = raw_env([scene], npc=npc, max_cycles=2)
        env.reset(seed=0)
        driven[name] = env.sim.policy_driven
        colors = role_colors(scene, env.sim.external, env.sim.policy_driven)
        assert (colors[env.sim.external] == SDC_COLOR).all()
        assert ((colors == REPLAY_COLOR).all(1) == ~(env.sim.policy_driven | env.sim.external)).all()
    assert entering.sum() == 4 and driven["model"][entering].all()  # the model drives them once they enter
    assert not driven["idm"][entering].any() and driven["idm"].sum() == scene.valid[:, cur].sum() - 1
    assert not driven["replay"].any()  # every NPC replays its log: grey


def test_a_scene_too_long_to_fit_is_followed_around_the_sdc() -> None:
    """A straight highway whose agents span hundreds of metres would be a thin strip of few-pixel cars:
    the default view follows the sdc at FOLLOW_RADIUS instead; a compact scene keeps the fitted view."""
    from helpers import bundle_scene

    from trajeglish_env.render import FOLLOW_RADIUS, MAX_FITTED_RADIUS

    long = bundle_scene("highway-highway-999000")
    compact = bundle_scene("highway-roundabout-999000")
    for scene, follows in ((long, True), (compact, False)):
        r = SceneRenderer(scene, config=RenderConfig(200, 200, title=False))
        try:
            assert (r._fitted_view()[1] > MAX_FITTED_RADIUS) == follows and r._follow == follows
            r.frame(scene.current_index + 5)
            half = (r.ax.get_ylim()[1] - r.ax.get_ylim()[0]) / 2
            assert half == (FOLLOW_RADIUS if follows else r._fitted_view()[1])
        finally:
            r.close()
    asked = SceneRenderer(long, config=RenderConfig(200, 200, view_radius=400.0, title=False))
    assert not asked._follow  # a radius asked for is kept
    asked.close()
