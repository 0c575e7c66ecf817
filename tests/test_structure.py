"""The package's shape: no import cycle among its modules, no module over 500 lines, and one sampling
configuration whose defaults the env, the CLI, the policies and ``evaluate`` all share."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

import trajeglish_env
from trajeglish_env.cli import build_parser
from trajeglish_env.env import TrajeglishNPC
from trajeglish_env.evaluation import EvalConfig
from trajeglish_env.sampler.config import DEFAULT_TEMPERATURE, SamplingConfig

PACKAGE = Path(trajeglish_env.__file__).parent


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_level_imports(path: Path, modules: set[str], in_functions: bool = False) -> set[str]:
    """The package modules a module imports when it is imported (module level, not under
    ``if TYPE_CHECKING``; imports inside functions run later, when called, and count only with
    ``in_functions``)."""
    tree = ast.parse(path.read_text())
    found: set[str] = set()
    stack = [n for n in tree.body if not (isinstance(n, ast.If) and "TYPE_CHECKING" in ast.dump(n.test))]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) and not in_functions:
            continue  # runs when called, not on import
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        found |= {n for n in names if n in modules}
        stack.extend(ast.iter_child_nodes(node))
    return found


def import_graph(in_functions: bool = False) -> dict[str, set[str]]:
    paths = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {m: module_level_imports(p, set(paths), in_functions) - {m} for m, p in paths.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph (depth-first search), or None."""
    done: set[str] = set()
    trail: list[str] = []

    def visit(m: str) -> list[str] | None:
        trail.append(m)
        for n in sorted(graph[m]):
            if n in trail:
                return trail[trail.index(n) :] + [n]
            if n not in done and (cycle := visit(n)):
                return cycle
        trail.pop()
        done.add(m)
        return None

    for m in sorted(graph):
        if m not in done and (cycle := visit(m)):
            return cycle
    return None


def test_no_import_cycle_in_the_package() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]  # the search finds one
    graph = import_graph()
    assert len(graph) > 80 and "trajeglish_env.env.scene_state" in graph["trajeglish_env.env.batch_outcomes"]
    cycle = find_cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle or [])}"


def test_data_flows_one_way() -> None:
    """Scenario data -> tokenizer -> model -> sampler -> environment: no stage imports a later one, on
    import or inside a function (the tokenizer's motion envelope reads the vehicle limits from
    ``kinematics``, not the env; the sampler's road edges come from ``batch_geometry``)."""
    later = {
        "trajeglish_env.tokenizer": ("trajeglish_env.model", "trajeglish_env.sampler", "trajeglish_env.env"),
        "trajeglish_env.model": ("trajeglish_env.sampler", "trajeglish_env.env"),
        "trajeglish_env.sampler": ("trajeglish_env.env",),
    }
    wrong = sorted(
        f"{m} imports {n}"
        for m, imports in import_graph(in_functions=True).items()
        for stage, banned in later.items()
        if m == stage or m.startswith(stage + ".")
        for n in imports
        if any(n == b or n.startswith(b + ".") for b in banned)
    )
    assert not wrong, wrong


def test_the_package_never_imports_policies() -> None:
    """``policies/`` builds on ``trajeglish_env``, never the other way round (imports inside functions
    count too)."""
    policies = {"policies"} | {
        f"policies.{Path(p).stem}" for p in Path(PACKAGE.parent, "policies").glob("*.py")
    }
    wrong = sorted(
        f"{module_name(p)} imports {n}"
        for p in PACKAGE.rglob("*.py")
        for n in module_level_imports(p, policies, in_functions=True)
    )
    assert not wrong, wrong
    # the scan sees an import of policies where there is one
    assert module_level_imports(Path(PACKAGE.parent, "examples", "train_ppo_ego.py"), policies, True)


def test_no_module_over_500_lines() -> None:
    long = {
        str(p.relative_to(PACKAGE)): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > 500
    }
    assert long == {}


def test_one_sampling_default_for_env_cli_policies_and_evaluate() -> None:
    from policies.learned import TrajeglishPolicy

    env_default = TrajeglishNPC().sampling
    assert env_default == SamplingConfig() and env_default.temperature == DEFAULT_TEMPERATURE
    assert EvalConfig().sampling == env_default and EvalConfig().temperatures == (env_default.temperature,)
    parser = build_parser()
    evaluate = parser.parse_args(["evaluate", "--data", "d"])
    rollout = parser.parse_args(["rollout", "--scenario", "s", "--out", "o.gif"])
    assert (
        evaluate.temperature == [env_default.temperature] and rollout.temperature == env_default.temperature
    )
    assert evaluate.cache_dtype == rollout.cache_dtype == env_default.cache_dtype
    assert evaluate.top_p == rollout.top_p == env_default.top_p
    assert (not evaluate.no_green_rule) == env_default.guard_green  # the green rule is on by default
    from trajeglish_env.cli_eval import guard_rules

    rules = {
        "guard_green": True,
        "guard_wrong_way": True,
        "guard_road_ahead": 5.0,
        "guard_step_change": env_default.guard_step_change,
        "guard_stall_steps": env_default.guard_stall_steps,
        "guard_follow_decel": env_default.guard_follow_decel,
    }
    assert guard_rules(evaluate, True) == guard_rules(rollout, True) == rules
    assert rules == {k: getattr(env_default, k) for k in rules}  # the CLI's defaults are the env's
    assert env_default.guard_road_ahead == 5.0 and env_default.guard_step_change == 0.5
    assert evaluate.subsets == env_default.subsets
    assert TrajeglishPolicy.__init__.__defaults__ == (None, None)  # None: SamplingConfig()


def test_the_old_dataset_module_name_is_a_deprecated_alias() -> None:
    import importlib
    import sys

    import pytest

    from trajeglish_env.training.dataset import WindowDataset

    sys.modules.pop("trajeglish_env.dataset", None)
    with pytest.warns(DeprecationWarning, match="moved to trajeglish_env.training.dataset"):
        old = importlib.import_module("trajeglish_env.dataset")
    assert old.WindowDataset is WindowDataset


def evaluate_with(monkeypatch, *argv: str) -> dict:
    """Run ``trajeglish evaluate --data d ARGV`` with the evaluation itself replaced: the checkpoints and
    config it would have been given."""
    import trajeglish_env.evaluation as evaluation
    from trajeglish_env.cli_eval import cmd_evaluate

    seen = {}

    def fake_evaluate(data, ckpts, config, *args, **kwargs):
        seen.update(ckpts=ckpts, config=config)
        return {"scenes": 0}

    monkeypatch.setattr(evaluation, "evaluate", fake_evaluate)
    cmd_evaluate(build_parser().parse_args(["evaluate", "--data", "d", *argv]))
    return seen


def test_evaluate_subsets_reach_the_sampling_config(monkeypatch) -> None:
    """``evaluate --subsets cover`` samples with ``SamplingConfig(subsets="cover")``."""
    seen = evaluate_with(monkeypatch, "--subsets", "cover", "--processes", "1")
    assert seen["config"].sampling.subsets == "cover"


def test_evaluate_takes_the_shipped_model_by_name(monkeypatch) -> None:
    """``evaluate --ckpt ref=shipped`` scores the pretrained model as ``ref`` (as ``scorecard`` and ``train
    --init`` name it); a missing file is still refused by name."""
    from trajeglish_env.checkpoint import CheckpointError, load_pretrained

    seen = evaluate_with(monkeypatch, "--ckpt", "ref=shipped", "--processes", "1")
    assert list(seen["ckpts"]) == ["ref"]
    want = load_pretrained().model.state_dict()
    got = seen["ckpts"]["ref"].model.state_dict()
    assert got.keys() == want.keys() and all(torch.equal(got[k].cpu(), want[k]) for k in want)
    with pytest.raises(CheckpointError, match="no/such.pt: no such checkpoint file"):
        evaluate_with(monkeypatch, "--ckpt", "x=no/such.pt")


def test_the_package_version_is_pyprojects_and_the_cli_prints_it(capsys) -> None:
    """A release bumps one number: pyproject's version is the package's ``__version__`` (pip keeps an
    installed wheel of the same version, so an unbumped release is silently not installed)."""
    import tomllib

    import trajeglish_env
    from trajeglish_env.cli import main

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    assert project["version"] == trajeglish_env.__version__
    with pytest.raises(SystemExit) as exited:
        main(["--version"])
    assert (
        exited.value.code == 0 and capsys.readouterr().out.strip() == f"trajeglish_env {project['version']}"
    )
