"""The import structure of nmjax, read from the source: no cycles, and the data modules' layering.

Imports inside functions count as much as those at the top of a module: a lazy import hides a
cycle from the interpreter, not from the reader.
"""

from __future__ import annotations

import ast
from pathlib import Path

import nmjax

SRC = Path(nmjax.__file__).parent


def module_name(path: Path) -> str:
    parts = ["nmjax", *path.relative_to(SRC).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(SRC.rglob("*.py"))}


def imported_modules(name: str, skip_functions: frozenset[str] = frozenset()) -> set[str]:
    """The nmjax modules that module `name` imports anywhere in its source.

    `from nmjax.data import layout` counts as nmjax.data.layout; `from nmjax.config import X` as
    nmjax.config. Functions named in `skip_functions` (at module level) are not read.
    """
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), filename=str(path))
    body = [
        node
        for node in tree.body
        if not (isinstance(node, ast.FunctionDef) and node.name in skip_functions)
    ]
    found = set()
    for node in (sub for top in body for sub in ast.walk(top)):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in MODULES else base)
    return {m for m in found if m in MODULES and m != name}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of `graph` as a list of modules (first == last), or None."""
    state: dict[str, str] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_find_cycle_reports_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_reader_sees_lazy_and_relative_imports():
    # datasets imports layout at the top; the trainer imports the generator inside train().
    assert "nmjax.data.layout" in imported_modules("nmjax.data.datasets")
    assert "nmjax.data.synthetic" in imported_modules("nmjax.train.skel")


def test_no_import_cycle_inside_nmjax():
    graph = {name: imported_modules(name) for name in MODULES}
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_datasets_prepare_and_synthetic_depend_on_layout_not_on_each_other():
    data = {"nmjax.data.datasets", "nmjax.data.prepare", "nmjax.data.synthetic"}
    # The prepare-data command dispatches synthetic names to the generator and real ones to the
    # converter; it lives in the CLI package (issue 16), so no exemption is needed here.
    for name in sorted(data):
        imports = imported_modules(name)
        assert not imports & data, f"{name} imports {sorted(imports & data)}"
        # prepare writes through nmjax.data.streaming, the writer every real-set reader shares
        through = (
            imported_modules("nmjax.data.streaming") if name == "nmjax.data.prepare" else set()
        )
        assert "nmjax.data.layout" in imports | through, name
    assert "nmjax.data.streaming" in imported_modules("nmjax.data.prepare")
    # nmjax.parents (NumPy only, importing no nmjax module) reads a tree's file conventions.
    assert imported_modules("nmjax.data.layout") <= {
        "nmjax.atomic",
        "nmjax.config",
        "nmjax.config_io",
        "nmjax.parents",
    }
    assert imported_modules("nmjax.parents") == set()
    assert imported_modules("nmjax.data.bodies") == set()


def package(name: str) -> set[str]:
    """The modules of package `name` (itself included)."""
    return {m for m in MODULES if m == name or m.startswith(name + ".")}


def imports_from_outside(name: str) -> set[str]:
    """The nmjax modules that any module of package `name` imports, its own left out."""
    inside = package(name)
    return set().union(*(imported_modules(m) for m in inside)) - inside


PURE_MATH = {"nmjax.geometry", "nmjax.keypoints", "nmjax.losses"}
APPLICATIONS = ("nmjax.evaluate", "nmjax.view", "nmjax.tasks")


def test_metrics_is_pure_math():
    outside = imports_from_outside("nmjax.metrics")
    assert outside <= PURE_MATH, f"nmjax.metrics imports {sorted(outside - PURE_MATH)}"


def test_data_imports_neither_metrics_nor_the_applications():
    above = set().union(*(package(p) for p in ("nmjax.metrics", *APPLICATIONS)))
    for name in sorted(package("nmjax.data")):
        assert not imported_modules(name) & above, (
            f"{name} imports {imported_modules(name) & above}"
        )


def test_tasks_sit_below_evaluate_and_view_which_stay_apart():
    # CLI -> view / evaluate -> tasks -> the trained models (docs/architecture.md): a task never
    # reaches up, and the two applications over the tasks do not lean on each other.
    for low, high in (
        ("nmjax.tasks", "nmjax.evaluate"),
        ("nmjax.tasks", "nmjax.view"),
        ("nmjax.tasks", "nmjax.cli"),
        ("nmjax.evaluate", "nmjax.view"),
        ("nmjax.view", "nmjax.evaluate"),
        ("nmjax.evaluate", "nmjax.cli"),
        ("nmjax.view", "nmjax.cli"),
    ):
        reached = imports_from_outside(low) & package(high)
        assert not reached, f"{low} imports {sorted(reached)}"
    assert "nmjax.train.trained" in imports_from_outside("nmjax.tasks")
    assert "nmjax.tasks" in imports_from_outside("nmjax.evaluate")


def test_the_application_packages_are_split_by_job_into_short_files():
    jobs = {
        "nmjax.evaluate": {"phase1", "phase2", "generation", "tables"},
        "nmjax.view": {"phase1", "phase2", "exported", "server", "viewer"},
        "nmjax.tasks": {"generate", "interpolate", "retarget"},
        "nmjax.metrics": {"sc", "skeleton_measures", "motion", "chamfer"},
    }
    for name, modules in jobs.items():
        assert MODULES[name].name == "__init__.py", f"{name} is not a package"
        assert {f"{name}.{m}" for m in modules} <= package(name)
        for module in sorted(package(name)):
            lines = len(MODULES[module].read_text().splitlines())
            assert lines <= 700, f"{module} has {lines} lines"
    # One reader of mesh and point files, one normalisation box.
    assert "nmjax.data.meshes" in imports_from_outside("nmjax.tasks")
    assert "nmjax.data.meshes" in imported_modules("nmjax.data.prepare")
    for name in ("nmjax.train.trained", "nmjax.data.pipeline", "nmjax.evaluate.phase1"):
        assert "nmjax.data.normalize" in imported_modules(name), name


def test_the_run_folder_sits_below_the_trainers():
    # run_folder is read by the trainers, the trained models' owner and the application modules;
    # it reads none of them (nor a model): what a folder holds is decided in one place below
    # every reader.
    above = ("nmjax.train", "nmjax.evaluate", "nmjax.view", "nmjax.tasks")
    above += ("nmjax.release", "nmjax.cli", "nmjax.bench", "nmjax.models", "nmjax.export")
    imports = imported_modules("nmjax.run_folder")
    assert not {m for m in imports if m.startswith(above)}, sorted(imports)
    assert imports <= {"nmjax.atomic", "nmjax.config", "nmjax.config_io", "nmjax.skeleton"}
    # The trainers' shared pieces read the run folder's names from it, never from a trainer.
    for name in ("nmjax.train.checkpoints", "nmjax.train.loop", "nmjax.train.metric_log"):
        assert not imported_modules(name) & {"nmjax.train.skel", "nmjax.train.dyn"}


def test_a_trained_model_has_one_owner_below_both_trainers():
    # Restoring a detector or a dynamics model for inference needs no trainer, and both
    # trainers finish their runs through it.
    assert not imported_modules("nmjax.train.trained") & {"nmjax.train.skel", "nmjax.train.dyn"}
    for trainer in ("nmjax.train.skel", "nmjax.train.dyn", "nmjax.train.dyn_inputs"):
        assert "nmjax.train.trained" in imported_modules(trainer), trainer
    assert "nmjax.runs" not in MODULES


def test_no_module_is_over_700_lines_except_the_kernel_collection():
    # A file a newcomer can read in one sitting; the CPU convolution kernels are one collection
    # of alternatives kept side by side on purpose (docs/architecture.md §2).
    long = {
        name: lines
        for name, path in MODULES.items()
        if (lines := len(path.read_text().splitlines())) > 700
    }
    assert set(long) <= {"nmjax.models.conv_kernels"}, long


def test_config_io_reads_no_configuration_class():
    # config.py builds its presets with config_io's functions; the reverse would be a cycle.
    assert imported_modules("nmjax.config_io") == set()
    assert "nmjax.config_io" in imported_modules("nmjax.config")


# The layers of docs/architecture.md, lowest first: a module imports from its own layer or below,
# never above (the command line -> the applications -> the tasks -> the trainers and the trained
# models' owner -> the run folder -> models, data and pictures -> pure math and the base modules).
LAYERS = (
    (
        "nmjax",
        "nmjax.geometry",
        "nmjax.keypoints",
        "nmjax.losses",
        "nmjax.metrics",
        "nmjax.skeleton",
        "nmjax.skeleton_refine",
        "nmjax.parents",
        "nmjax.atomic",
        "nmjax.config",
        "nmjax.config_io",
        "nmjax.provenance",
    ),
    ("nmjax.models", "nmjax.data", "nmjax.viz"),
    ("nmjax.run_folder", "nmjax.rows"),
    ("nmjax.train",),
    ("nmjax.tasks",),
    ("nmjax.evaluate", "nmjax.view", "nmjax.release", "nmjax.export", "nmjax.bench", "nmjax.rig"),
    ("nmjax.cli",),
)


def layer_of(name: str) -> int:
    """The index in LAYERS of module `name`: its own entry or its package's (longest wins)."""
    found = [
        (len(entry), i)
        for i, entries in enumerate(LAYERS)
        for entry in entries
        if name == entry or (entry != "nmjax" and name.startswith(entry + "."))
    ]
    if not found:
        raise KeyError(f"{name} is in no layer of LAYERS; place it")
    return max(found)[1]


def test_every_module_imports_only_from_its_layer_or_below():
    upward = [
        f"{name} (layer {layer_of(name)}) imports {other} (layer {layer_of(other)})"
        for name in sorted(MODULES)
        for other in sorted(imported_modules(name))
        if layer_of(other) > layer_of(name)
    ]
    assert not upward, "\n".join(upward)


def test_the_layer_rule_sees_an_upward_import():
    assert layer_of("nmjax.train.loop") < layer_of("nmjax.tasks") < layer_of("nmjax.cli.train")
    assert layer_of("nmjax.metrics.sc") == layer_of("nmjax.geometry") == 0
    assert layer_of("nmjax.run_folder") < layer_of("nmjax.train.skel")
