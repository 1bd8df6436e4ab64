"""The house plan's import rules (docs/development.md#the-house-plan): the library never imports
a stage, and no module imports itself through others (imports inside functions count too)."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _graph() -> dict[str, set[str]]:
    modules = {}
    for path in [*ROOT.glob("worldenv_core/**/*.py"), *ROOT.glob("stages/**/*.py")]:
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        modules[name] = path
    graph = {}
    for name, path in modules.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                deps |= {node.module, *(f"{node.module}.{a.name}" for a in node.names)}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
        # a package's __init__ re-exporting its own modules is not a cycle
        graph[name] = {d for d in deps if d in modules and d != name and not d.startswith(name + ".")}
    return graph


def test_the_library_never_imports_a_stage():
    graph = _graph()
    assert [(m, d) for m, ds in graph.items() if m.startswith("worldenv_core") for d in ds
            if d.startswith("stages")] == []


def test_no_import_cycle():
    graph, state, cycles = _graph(), {}, []

    def visit(module, path):
        state[module] = "open"
        for dep in sorted(graph[module]):
            if state.get(dep) == "open":
                cycles.append(path[path.index(dep):] + [dep])
            elif dep not in state:
                visit(dep, path + [dep])
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert cycles == []


# Modules whose tests live in another file than their mirror (tests/<path>/test_<name>.py), and which:
# the covering file must exist and name the module (an import, or its name in the text).
COVERED_BY = {
    "worldenv_core/errors.py": "tests/worldenv_core/test_cli.py",
    "worldenv_core/report.py": "tests/stages/test_report.py",
    "worldenv_core/robot.py": "tests/stages/collect/test_run.py",
    "worldenv_core/metrics.py": "tests/worldenv_core/models/test_worldsim.py",
    "worldenv_core/locks.py": "tests/test_faults.py",
    "worldenv_core/training/batches.py": "tests/worldenv_core/training/test_trainer.py",
    "worldenv_core/training/checkpoints.py": "tests/worldenv_core/training/test_trainer.py",
    "worldenv_core/envs/collection.py": "tests/stages/collect/test_run.py",
    "worldenv_core/envs/expert/planner.py": "tests/worldenv_core/envs/expert/test_expert.py",
    "worldenv_core/envs/expert/context.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "worldenv_core/envs/expert/motion.py": "tests/worldenv_core/envs/expert/test_expert.py",
    "worldenv_core/envs/expert/grasping.py": "tests/worldenv_core/envs/expert/test_expert.py",
    "worldenv_core/envs/expert/pick_place.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "worldenv_core/envs/expert/push.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "worldenv_core/envs/expert/articulated/joints.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "stages/evaluate/run.py": "tests/stages/train_policy/test_run.py",  # train_policy -> collect -> evaluate
    "stages/evaluate/evaluation.py": "tests/stages/train_policy/test_run.py",
    "worldenv_core/envs/expert/articulated/door.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "worldenv_core/envs/expert/articulated/drawer.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "worldenv_core/envs/expert/articulated/knob.py": "tests/worldenv_core/envs/expert/test_articulated.py",
    "worldenv_core/kinematics/camera.py": "tests/worldenv_core/kinematics/test_kinematics.py",
    "worldenv_core/kinematics/chain.py": "tests/worldenv_core/kinematics/test_kinematics.py",
    "worldenv_core/kinematics/next_state.py": "tests/worldenv_core/kinematics/test_kinematics.py",
    "worldenv_core/kinematics/action_map.py": "tests/worldenv_core/kinematics/test_kinematics.py",
    "worldenv_core/models/text.py": "tests/stages/post_train_loop/test_run.py",
    "worldenv_core/models/checkpoint.py": "tests/worldenv_core/models/test_policy.py",
    "worldenv_core/models/reflector_data.py": "tests/worldenv_core/models/test_reflector.py",
    "worldenv_core/models/worldsim_data.py": "tests/worldenv_core/models/test_worldsim.py",
    "worldenv_core/data/mcap_io/png.py": "tests/worldenv_core/data/mcap_io/test_write.py",
    "worldenv_core/data/mcap_io/format.py": "tests/worldenv_core/data/mcap_io/test_write.py",
    "analysis/refit_kinematics.py": "tests/stages/train_worldsim/test_run.py",   # on that file's world model
    "analysis/fidelity_settings.py": "tests/stages/train_worldsim/test_run.py",
    "analysis/sweep_packs.py": "tests/stages/post_train_loop/test_run.py",        # on that file's LOOP run
}


def test_every_module_has_a_mirrored_test_or_a_named_covering_one():
    """tests/ mirrors the source tree; a module tested elsewhere names its covering file above (one
    that exists and names it), and a stage's other modules are covered by its end-to-end test_run.py."""
    missing = []
    for path in sorted(p for top in ("worldenv_core", "stages", "analysis") for p in (ROOT / top).rglob("*.py")):
        rel = path.relative_to(ROOT)
        if path.name in ("__init__.py", "__main__.py") or (ROOT / "tests" / rel.parent / f"test_{path.stem}.py").exists():
            continue
        if rel.parts[0] == "stages":  # stages/<stage>/x.py: the stage's end-to-end test runs it
            cover = ROOT / "tests" / "stages" / (rel.parts[1] if len(rel.parts) > 2 else "") / "test_run.py"
            if len(rel.parts) > 2 and cover.exists():
                continue
        cover = ROOT / COVERED_BY.get(str(rel), "-")
        dotted = str(rel.with_suffix("")).replace("/", ".")
        # the module, or the package it is part of (the expert's parts, run through the expert)
        words = (dotted, path.stem, *(dotted.rsplit(".", k)[0] for k in (1, 2) if dotted.count(".") - k >= 2))
        if not (cover.is_file() and any(w in cover.read_text() for w in words)):
            missing.append(str(rel))
    assert not missing, f"no mirrored test file and no named covering test (COVERED_BY) for {missing}"
