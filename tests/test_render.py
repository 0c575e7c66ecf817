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


def test_the_title_counts_the_agents_present_of_every_track(straight_scene: Scenario) -> None:
    """The title said ``agents=50`` (present at its step) while `render --json` said ``agents: 83`` (every
    track): each now says which it counts."""
    r = SceneRenderer(straight_scene, config=RenderConfig(96, 96))
    try:
        r.frame(10)  # the last of the 6 agents enters at step 20
        assert r._text.get_text().endswith("  t=+0.0s  agents=5 now of 6")
        r.frame(30)
        assert r._text.get_text().endswith("agents=6 now of 6")
    finally:
        r.close()


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


def test_outputs_are_checked_before_any_frame_is_drawn(
    tmp_path, straight_scene: Scenario, monkeypatch
) -> None:
    """A missing ffmpeg was a traceback after every frame was rendered (and `rollout` sampled first); a
    folder or a file in the way failed at the final rename, naming the temporary file."""
    from trajeglish_env.render import check_output, write_video

    (tmp_path / "adir.png").mkdir()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match="adir.png: is a folder"):
        save_render(straight_scene, tmp_path / "adir.png")
    with pytest.raises(ValueError, match="afile is a file, not a folder"):
        save_render(straight_scene, tmp_path / "afile" / "x.gif")
    with pytest.raises(ValueError, match="GIF at 100 fps"):
        save_render(straight_scene, tmp_path / "fast.gif", fps=100)
    import imageio_ffmpeg

    def no_ffmpeg() -> str:
        raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", no_ffmpeg)
    drawn = []

    def frames():
        drawn.append(1)
        yield np.zeros((16, 16, 3), np.uint8)

    with pytest.raises(ValueError, match="MP4 needs ffmpeg.*IMAGEIO_FFMPEG_EXE"):
        write_video(frames(), tmp_path / "x.mp4")
    assert not drawn and check_output(tmp_path / "y.gif", (".gif",)) == tmp_path / "y.gif"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir.png", "afile"]


def test_videos_are_written_frame_by_frame_at_their_size(tmp_path) -> None:
    """Every frame was kept in a list before encoding (1.4 GB for a 610-step GIF); an MP4 of a size not a
    multiple of 8 was resized."""
    from trajeglish_env.render import write_video

    seen = []

    def frames(n: int):
        for k in range(n):
            seen.append(k)
            yield np.full((50, 66, 3), 20 * k, np.uint8)

    gif = write_video(frames(5), tmp_path / "a.gif", fps=10)
    assert seen == list(range(5)) and len(imageio.mimread(gif)) == 5
    mp4 = write_video(frames(4), tmp_path / "a.mp4", fps=10)
    reader = imageio.get_reader(mp4)
    assert reader.get_data(0).shape == (50, 66, 3)
    reader.close()


def test_a_tall_picture_keeps_the_radius_across_its_width(straight_scene: Scenario) -> None:
    r = SceneRenderer(straight_scene, config=RenderConfig(100, 200, view_radius=10.0, title=False))
    try:
        assert np.diff(r.ax.get_xlim())[0] == pytest.approx(20.0)
        assert np.diff(r.ax.get_ylim())[0] == pytest.approx(40.0)
    finally:
        r.close()


def test_the_view_moves_on_to_the_next_external_agent_and_holds_in_gaps(straight_scene: Scenario) -> None:
    """The view followed the first external agent only: when its episode ended it jumped to the whole
    scene and the agents still driving left the picture; a gap in a followed track did the same."""
    from trajeglish_env.render import EpisodeRenderer

    sc = straight_scene
    valid = sc.valid.copy()
    external = np.zeros(sc.num_agents, bool)
    external[[1, 2]] = True
    valid[1, 20:] = False  # agent 1's episode ends at step 20
    er = EpisodeRenderer(sc, sc.xyh, valid, external, ~external, size=100, radius=10.0)
    try:
        assert er.renderer.focus_at(19) == 1 and er.renderer.focus_at(20) == 2
        er.frame(25)
        assert np.mean(er.renderer.ax.get_xlim()) == pytest.approx(sc.xyh[2, 25, 0])
        valid[2, 30:] = False  # nobody left to follow: the last view stays
        er.frame(35)
        assert np.mean(er.renderer.ax.get_xlim()) == pytest.approx(sc.xyh[2, 25, 0])
    finally:
        er.close()


def test_human_mode_draws_once_per_timestep(monkeypatch) -> None:
    """With several external agents the window was redrawn after every agent's action (40x slower)."""
    from helpers import bundle_scene

    from trajeglish_env.env import raw_env

    scene = bundle_scene("highway-roundabout-999000")
    env = raw_env([scene], npc="replay", external="all", render_mode="human", max_cycles=3)
    calls = []
    monkeypatch.setattr(type(env), "render", lambda self: calls.append(self.sim.t))
    env.reset(seed=0)
    agents = len(env.agents)
    assert agents > 1 and calls == [scene.current_index]
    for _ in range(agents):
        env.step(env.action_space(env.agent_selection).sample())
    assert calls == [scene.current_index, scene.current_index + 1]


def test_a_legend_names_the_colours_the_picture_uses(straight_scene: Scenario) -> None:
    """Pictures had no key: the colours' meanings were in the README only."""
    r = SceneRenderer(straight_scene, config=RenderConfig(200, 200, legend=True))
    try:
        labels = [t.get_text() for t in r.ax.get_legend().get_texts()]
        assert labels[:2] == ["sdc / external", "vehicle"] and "log replay" not in labels
    finally:
        r.close()
    plain = SceneRenderer(straight_scene, config=RenderConfig(200, 200))
    assert plain.ax.get_legend() is None
    plain.close()


def test_human_mode_without_a_display_says_no_window_shows(monkeypatch) -> None:
    """On a headless machine SDL fell back to its offscreen driver silently: no window, no word."""
    from helpers import bundle_scene

    from trajeglish_env.render import EpisodeRenderer

    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    sc = bundle_scene("highway-roundabout-999000")
    external = np.zeros(sc.num_agents, bool)
    external[sc.sdc] = True
    er = EpisodeRenderer(sc, sc.xyh, sc.valid, external, ~external, size=64, radius=20.0)
    try:
        with pytest.warns(UserWarning, match="no display was found"):
            er.show(er.frame(sc.current_index))
    finally:
        er.close()


def test_env_frames_carry_the_legend_when_asked() -> None:
    """The env's frames never had a key of the colours (which one is the ego: red); `render_legend=True`."""
    import trajeglish_env

    frames = []
    for legend in (False, True):
        env = trajeglish_env.env(npc="idm", render_mode="rgb_array", render_legend=legend)
        env.reset(seed=0)
        frames.append(env.render())
    assert frames[0].shape == frames[1].shape and (frames[0] != frames[1]).any()
    with pytest.raises(TypeError, match="render_legend must be a bool"):
        trajeglish_env.env(render_legend="yes")
