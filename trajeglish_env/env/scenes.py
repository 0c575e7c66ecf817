"""Where the environment's scenes come from: a list of Scenarios, scenario files or a directory of shards,
the built-in highway-env generator, or (by default) the small bundle of held-out scenes shipped in the
package. Also builds that bundle (``python -m trajeglish_env.env.scenes --out FILE``)."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Protocol

import numpy as np

from trajeglish_env.scenario import Scenario, ScenarioError
from trajeglish_env.scenario_io import (
    count_scenarios,
    list_scenario_files,
    load_scenarios,
    no_scenario_files_message,
    save_scenarios,
    scenario_ids,
)

BUNDLE_ASSET = "scenes_bundle.scn.npz"
BUNDLE_SEED = 999_000  # highway scenes of the bundle use seeds 999_000+ (training data uses small seeds)
GENERATOR_PREFIX = "highway"


class SceneSet(Protocol):
    """A collection of scenes the env picks from at every reset."""

    def __len__(self) -> int: ...

    def get(self, index: int) -> Scenario:
        """The scene at ``index``."""

    def index_of(self, name: str) -> int:
        """The index of the scene whose ``scenario_id`` is ``name`` (UnknownSceneError if none)."""


class UnknownSceneError(KeyError, ValueError):
    """No scene of a scene set has the requested scenario_id (a KeyError, and a ValueError for callers that
    treat it as bad input, like the command line)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class SceneList:
    """Scenes held in memory (a user's list, or the shipped bundle).

    Each scene is validated once here (``check=False`` for scenes that were validated when loaded).
    """

    def __init__(self, scenes: Sequence[Scenario], where: str = "scenes", check: bool = True):
        if not scenes:
            raise ValueError(f"{where}: no scenes given")
        for i, sc in enumerate(scenes):
            if not isinstance(sc, Scenario):
                raise TypeError(f"{where}[{i}]: expected a Scenario, got {type(sc).__name__}")
            if check:
                _validate(sc, f"{where}[{i}]")
        self.scenes = tuple(scenes)
        self.where = where

    def __len__(self) -> int:
        return len(self.scenes)

    def get(self, index: int) -> Scenario:
        """The scene at ``index``."""
        return self.scenes[index]

    def index_of(self, name: str) -> int:
        """The index of the scene whose ``scenario_id`` is ``name`` (UnknownSceneError if none)."""
        for i, sc in enumerate(self.scenes):
            if sc.scenario_id == name:
                return i
        ids = [sc.scenario_id for sc in self.scenes[:20]]
        raise UnknownSceneError(
            f"{self.where}: no scene with scenario_id {name!r} (have {ids}{'...' if len(self) > 20 else ''})"
        )


class CheckedScenes:
    """A user's own SceneSet whose scenes are validated the first time each Scenario object is served."""

    def __init__(self, scenes: SceneSet):
        self.scenes = scenes
        self._checked: weakref.WeakSet[Scenario] = weakref.WeakSet()

    def __len__(self) -> int:
        return len(self.scenes)

    def get(self, index: int) -> Scenario:
        """The scene at ``index``."""
        sc = self.scenes.get(index)
        if sc not in self._checked:
            if not isinstance(sc, Scenario):
                raise TypeError(f"scenes.get({index}): expected a Scenario, got {type(sc).__name__}")
            _validate(sc, f"scenes.get({index})")
            self._checked.add(sc)
        return sc

    def index_of(self, name: str) -> int:
        """The index of the scene whose ``scenario_id`` is ``name`` (UnknownSceneError if none)."""
        return self.scenes.index_of(name)


def _validate(scenario: Scenario, where: str) -> None:
    """Validate a user's scene; the error says where it came from."""
    try:
        scenario.validate()
    except ScenarioError as exc:
        raise ScenarioError(f"{where}: {exc}") from exc


# Bytes of scene arrays a directory of shards keeps loaded (the shards drawn last; at least the current one).
SHARD_CACHE_BYTES = 512 * 2**20


def scene_bytes(sc: Scenario) -> int:
    """Bytes held by the arrays of ``sc``."""
    values = (getattr(sc, f.name) for f in dataclasses.fields(sc))
    return sum(v.nbytes for v in values if isinstance(v, np.ndarray))


class SceneFiles:
    """Scenes in scenario files (a directory of shards is indexed once; a shard is loaded when needed and kept
    while the loaded shards hold at most :data:`SHARD_CACHE_BYTES` of arrays, least recently used first out).

    Keeping them matters beyond the load time: the engines cache per scene object (map chunks, road edges,
    signals, lanes), so a shard loaded again made new objects and new cache entries at every draw (16 scenes
    in 2 shards: 277 -> 675 MB over 400 short episodes, resets 17 ms against 5; the RL audit of stop 82)."""

    def __init__(self, path: str | os.PathLike[str]):
        self.files = list_scenario_files(path)
        if not self.files:
            raise ValueError(no_scenario_files_message([path]))
        self.where = str(path)
        self._counts = np.array([count_scenarios(f) for f in self.files], dtype=np.int64)
        self._starts = np.concatenate([[0], np.cumsum(self._counts)])
        if len(self) == 0:
            raise ScenarioError(
                f"{path}: the scenario files hold no scenes ({len(self.files)} empty shard(s))"
            )
        self._shards: OrderedDict[int, tuple[list[Scenario], int]] = OrderedDict()  # shard -> scenes, bytes
        self._ids: dict[str, int] | None = None  # scenario id -> index, read on the first reset by id

    def __len__(self) -> int:
        return int(self._starts[-1])

    def get(self, index: int) -> Scenario:
        """The scene at ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"{self.where}: scene {index} out of range for {len(self)} scenes")
        shard = int(np.searchsorted(self._starts, index, side="right") - 1)
        return self._shard(shard)[index - int(self._starts[shard])]

    def _shard(self, shard: int) -> list[Scenario]:
        """The scenes of ``shard``, loaded once while the cache has room for them."""
        hit = self._shards.get(shard)
        if hit is not None:
            self._shards.move_to_end(shard)
            return hit[0]
        scenes = load_scenarios(self.files[shard])
        self._shards[shard] = (scenes, sum(scene_bytes(sc) for sc in scenes))
        while len(self._shards) > 1 and sum(b for _, b in self._shards.values()) > SHARD_CACHE_BYTES:
            self._shards.popitem(last=False)
        return scenes

    def index_of(self, name: str) -> int:
        """The index of the scene with this id: the ids are read once (headers only, no scene loaded);
        an id held twice resolves to its first scene."""
        if self._ids is None:
            self._ids = {}
            for shard, path in enumerate(self.files):
                for i, sid in enumerate(scenario_ids(path)):
                    self._ids.setdefault(sid, int(self._starts[shard]) + i)
        if name not in self._ids:
            raise UnknownSceneError(f"{self.where}: no scene with scenario_id {name!r}")
        return self._ids[name]


class GeneratedScenes:
    """Fresh highway-env scenes: scene ``i`` is ``generate_scene(kinds[i % len(kinds)], seed=i)``.

    It holds ``size`` scenes (default 1,000,000) so a reset seed picks one; generation takes about a second.
    """

    def __init__(self, kinds: Sequence[str] = (), size: int = 1_000_000):
        from trajeglish_env.sources.highway import KINDS, check_kind

        self.kinds = tuple(kinds) or KINDS
        for kind in self.kinds:
            check_kind(kind)
        self.size = int(size)

    def __len__(self) -> int:
        return self.size

    def get(self, index: int) -> Scenario:
        """The scene at ``index``."""
        return _generated(self.kinds[index % len(self.kinds)], int(index))

    def index_of(self, name: str) -> int:
        # "highway-<kind>-<seed>" as written by the generator
        """The index of the scene whose ``scenario_id`` is ``name`` (UnknownSceneError if none)."""
        prefix, _, seed = name.rpartition("-")
        if not seed.isdigit() or not prefix.startswith(f"{GENERATOR_PREFIX}-"):
            raise UnknownSceneError(f"generated scenes: expected an id 'highway-<kind>-<seed>', got {name!r}")
        return int(seed)


@functools.lru_cache(maxsize=8)
def _generated(kind: str, seed: int) -> Scenario:
    from trajeglish_env.sources.highway import generate_scene

    return generate_scene(kind, seed)


def bundle_path() -> Path:
    """Path of the bundle of held-out scenes shipped in the package."""
    return Path(str(resources.files("trajeglish_env") / "assets" / BUNDLE_ASSET))


@functools.cache
def load_bundle() -> SceneList:
    """The shipped held-out scenes (read once per process)."""
    path = bundle_path()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the bundled scenes are missing from this installation")
    return SceneList(load_scenarios(path), where=str(path), check=False)  # load_scenarios validated them


def scene_set(scenes: object) -> SceneSet:
    """Turn what the user passed as ``scenes`` into a SceneSet.

    None: the shipped bundle; a Scenario or a list of them; a path to a scenario file or a directory of
    shards; ``"highway"`` or ``"highway:kind1,kind2"``: the built-in generator.
    """
    if scenes is None:
        return load_bundle()
    if isinstance(scenes, Scenario):
        return SceneList([scenes])
    if isinstance(scenes, str) and (scenes == GENERATOR_PREFIX or scenes.startswith(GENERATOR_PREFIX + ":")):
        kinds = [k for k in scenes.partition(":")[2].split(",") if k]
        return GeneratedScenes(kinds)
    if isinstance(scenes, (str, os.PathLike)):
        return SceneFiles(scenes)
    if isinstance(scenes, (list, tuple)):
        return SceneList(list(scenes))
    if isinstance(scenes, (SceneList, SceneFiles, GeneratedScenes, CheckedScenes)):
        return scenes  # already checked (a batched env shares one scene set among its envs)
    if all(hasattr(scenes, a) for a in ("__len__", "get", "index_of")):
        return CheckedScenes(scenes)  # type: ignore[arg-type]
    raise TypeError(
        "scenes: expected None (the bundled scenes), a Scenario, a list of Scenarios, a path to scenario "
        f"files, or 'highway[:kinds]', got {type(scenes).__name__}"
    )


def scene_index(option: object, scenes: SceneSet) -> int | None:
    """Index in ``scenes`` of the ``scene`` reset option: None (the caller draws one from its seed), an
    integer index (a Python or NumPy int; bools, floats and sequences are refused) or a scenario_id."""
    if option is None:
        return None
    if isinstance(option, str):
        return scenes.index_of(option)
    if isinstance(option, Scenario):  # its repr is the whole scene (11,000 characters): name it by its id
        raise TypeError(
            f"reset options: 'scene' must be a scene index (int) or a scenario_id (str), got the Scenario "
            f"{option.scenario_id!r} itself: pass options={{'scene': {option.scenario_id!r}}} (a scene of "
            "the env's scene set), or build the env with scenes=[scenario]"
        )
    if isinstance(option, (bool, np.bool_)) or not isinstance(option, (int, np.integer)):
        shown = repr(option)
        raise TypeError(
            f"reset options: 'scene' must be a scene index (int) or a scenario_id (str), "
            f"got {type(option).__name__} {shown[:80] + '...' if len(shown) > 80 else shown}"
        )
    index = int(option)
    if not 0 <= index < len(scenes):
        raise ValueError(
            f"reset options: 'scene' index {index} out of range: expected 0..{len(scenes) - 1} "
            f"({len(scenes)} scenes)"
        )
    return index


def build_bundle(out: str | os.PathLike[str], per_kind: int = 2, sumo_scenes: int = 4) -> Path:
    """Generate the shipped bundle: ``per_kind`` highway scenes of every kind (seeds from
    :data:`BUNDLE_SEED`) and ``sumo_scenes`` SUMO urban scenes (skipped when SUMO is not installed)."""
    from trajeglish_env.sources.highway import KINDS, generate_scene

    scenes = [generate_scene(kind, BUNDLE_SEED + i) for i in range(per_kind) for kind in KINDS]
    if sumo_scenes:
        try:
            from trajeglish_env.sources import sumo

            scenes += sumo.generate_shard(sumo.KINDS, BUNDLE_SEED, 0, sumo_scenes)
        except Exception as exc:  # SUMO missing or failing: the bundle is still usable without it
            print(f"SUMO scenes skipped: {exc}")
    return save_scenarios(out, scenes)


def main(argv: Sequence[str] | None = None) -> None:
    """Command line of :func:`build_bundle`."""
    parser = argparse.ArgumentParser(description=build_bundle.__doc__)
    parser.add_argument("--out", default=str(bundle_path()))
    parser.add_argument("--per-kind", type=int, default=2)
    parser.add_argument("--sumo-scenes", type=int, default=4)
    args = parser.parse_args(argv)
    path = build_bundle(args.out, args.per_kind, args.sumo_scenes)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
