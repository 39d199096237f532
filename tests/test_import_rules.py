"""The dependency rules of DESIGN.md §2, checked by parsing every module's imports."""

from __future__ import annotations

import ast
import contextlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calib", "sim_us", "twin", "hw", "bench")
THIRD_PARTY_ONLY_IN = {
    "rerun": {"bench/recording"},
    # The only modules that print: the command line and what it prints.
    "rich": {"bench/cli.py", "bench/console"},
    "distributed": {"bench/parallel.py"},
    "dask": {"bench/parallel.py"},
    "ur_rtde": {"hw"},
    "rtde_control": {"hw"},
    "rtde_receive": {"hw"},
    "cv2": {"hw"},
}
# calib and sim_us may use only these third-party packages (sim_us also embreex, the
# Embree binding trimesh itself uses for ray casting; numba compiles the localizer's
# search kernel).
SCIENTIFIC = {"numpy", "numba", "scipy", "skimage", "trimesh"}
# twin and hw may use only these calib modules (pure maths, records, errors).
CALIB_SHARED = {
    "calib.se3",
    "calib.records",
    "calib.errors",
    "calib.dh",
    "calib.files.dataset",
}


def _type_checking_only(tree: ast.AST) -> set[int]:
    """ids of the nodes inside ``if TYPE_CHECKING:`` blocks (imports for annotations
    alone, never executed)."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skip.update(id(n) for n in ast.walk(child))
    return skip


def _package(path: Path) -> list[str]:
    """The dotted package a module file belongs to, as parts."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return parts if parts[-1] == "__init__" and parts.pop() else parts[:-1]


def _lazy_nodes(tree: ast.AST) -> set[int]:
    """ids of the import nodes inside a function or method (run at call time)."""
    lazy: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for child in ast.walk(node):
                if isinstance(child, (ast.Import, ast.ImportFrom)):
                    lazy.add(id(child))
    return lazy


def imports_of(path: Path, lazy: bool = True, types: bool = False) -> set[str]:
    """The modules (and imported names, as ``module.name``) a file imports; without
    ``lazy``, only those imported when the module itself is imported; with ``types``, also
    those imported for annotations alone (``if TYPE_CHECKING:``)."""
    return _imports(ast.parse(path.read_text(encoding="utf-8")), _package(path), lazy, types)


def _imports(tree: ast.AST, package: list[str], lazy: bool = True, types: bool = False) -> set[str]:
    """:func:`imports_of` a parsed module of ``package`` (its dotted parts)."""
    names: set[str] = set()
    skip = set() if types else _type_checking_only(tree)
    if not lazy:
        skip |= _lazy_nodes(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve inside the package
                base = ".".join(package[: len(package) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            names.add(mod)
            names.update(f"{mod}.{a.name}" for a in node.names)
    return names


def modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            yield pkg, path


def test_there_are_modules_to_check():
    assert sum(1 for _ in modules()) >= 15


@pytest.mark.parametrize("pkg,path", list(modules()), ids=lambda v: str(v))
def test_import_rules(pkg, path):
    rel = path.relative_to(ROOT).as_posix()
    names = imports_of(path)
    tops = {n.split(".")[0] for n in names}
    for lib, allowed in THIRD_PARTY_ONLY_IN.items():
        if lib in tops:
            assert any(rel == a or rel.startswith(a + "/") for a in allowed), (
                f"{rel} imports {lib}, allowed only in {sorted(allowed)}"
            )
    stdlib = set(__import__("sys").stdlib_module_names)
    if pkg == "calib":
        # The dataset manifest (YAML, safe loader only) is the one file format calib owns.
        extra = {"yaml"} if rel == "calib/files/dataset.py" else set()
        foreign = tops - stdlib - SCIENTIFIC - extra - {pkg, "__future__"}
        assert not foreign, f"{rel} imports {sorted(foreign)}"
    if pkg == "sim_us":
        # sim_us may use the shared maths of calib (transforms, the pixel mapping, the
        # speed of sound in water).
        foreign = tops - stdlib - SCIENTIFIC - {pkg, "__future__", "calib", "embreex"}
        assert not foreign, f"{rel} imports {sorted(foreign)}"
        calib_mods = {n for n in names if n.startswith("calib.")}
        shared = ("se3", "image", "sound")
        bad = {m for m in calib_mods if m.split(".")[1] not in shared}
        assert not bad, f"{rel} imports {sorted(bad)}; sim_us may use calib.{shared}"
    if pkg == "twin":
        assert "hw" not in tops, f"{rel} imports hw"
    if pkg == "hw":
        assert "twin" not in tops and "sim_us" not in tops, f"{rel} imports twin/sim_us"
    if pkg in ("twin", "hw"):
        assert "bench" not in tops, f"{rel} imports bench"
        calib_mods = {n for n in names if n.startswith("calib.")}
        assert not {m for m in calib_mods if not any(m.startswith(c) for c in CALIB_SHARED)}, (
            f"{rel} imports {sorted(calib_mods)}; twin and hw may use only {sorted(CALIB_SHARED)}"
        )
    if pkg == "sim_us":
        assert not tops & {"twin", "bench", "hw"}, f"{rel} imports another package"


def _module_graph(pkg: str) -> dict[str, set[str]]:
    """Each module of ``pkg`` (dotted name) → the modules of ``pkg`` it imports, at any
    level and for any purpose (a function-level import to dodge a cycle counts as one, and
    so does an import for annotations alone)."""
    paths = {
        ".".join(p.relative_to(ROOT).with_suffix("").parts): p
        for p in sorted((ROOT / pkg).rglob("*.py"))
    }
    paths = {m.removesuffix(".__init__"): p for m, p in paths.items()}
    return {
        m: {n for n in imports_of(p, types=True) if n in paths and n != m and n != pkg}
        for m, p in paths.items()
    }


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (its modules in order), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return [*path[path.index(n) :], n]
            if n not in state and (found := visit(n)):
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_the_cycle_check_sees_function_level_and_type_only_imports():
    """An import inside a function (run at call time) or under ``if TYPE_CHECKING:`` (for
    annotations) still makes a module depend on another: the cycle check counts both, so
    neither hides a cycle (the layer check refuses the first outright)."""
    tree = ast.parse(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from .scenario import Scenario\n"
        "def check():\n    from .geometry import check_geometry\n"
    )
    package = ["bench", "config"]
    both = {"bench.config.scenario", "bench.config.geometry"}
    assert both <= _imports(tree, package, types=True)
    assert "bench.config.scenario" not in _imports(tree, package)
    assert not both & _imports(tree, package, lazy=False)


@pytest.mark.parametrize("pkg", ["calib", "sim_us", "twin", "hw", "bench"])
def test_no_import_cycles(pkg):
    """No module imports, directly or through others, the module importing it (lazy and
    annotation-only imports included): each package reads bottom-up."""
    cycle = _cycle(_module_graph(pkg))
    assert cycle is None, " → ".join(cycle)


#: bench's layers, top first (DESIGN.md §2): a module imports only from its own layer
#: or below. The command line; what it prints and writes; the jobs; the acquisitions,
#: the truth, the recording, parallel execution and grids of runs; the settings, random
#: streams, typed results (and their typed read, with the table model), progress and file
#: writing.
BENCH_LAYERS = (
    ("bench.cli", "bench.cli_parser"),
    ("bench.console", "bench.outputs"),
    ("bench.jobs",),
    (
        "bench.truth",
        "bench.acquire_sim",
        "bench.acquire_rig",
        "bench.parallel",
        "bench.grid",
        "bench.recording",
        "bench.snapshot",
        "bench.candidates",
        "bench.sequential",
    ),
    (
        "bench.sessions",
        "bench.config",
        "bench.results",
        "bench.summaries",
        "bench.tables",
        "bench.progress",
        "bench.files",
    ),
)


def _layer(module: str) -> int:
    for k, prefixes in enumerate(BENCH_LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return k
    raise AssertionError(f"{module} is in no layer of BENCH_LAYERS")


def _bench_modules() -> dict[str, Path]:
    paths = {
        ".".join(p.relative_to(ROOT).with_suffix("").parts): p
        for p in sorted((ROOT / "bench").rglob("*.py"))
    }
    return {m.removesuffix(".__init__"): p for m, p in paths.items() if m != "bench.__init__"}


@pytest.mark.parametrize("module", sorted(_bench_modules()))
def test_bench_imports_only_downwards_and_at_the_top(module):
    """Each bench module is in one layer and imports bench modules of its own layer or
    below, at module level only (no import inside a function to dodge an order). The
    command line (the top layer, which nothing imports) alone imports each command's
    modules inside the command, so that ``uscal --help`` does not wait seconds for the
    simulator; those imports too go downwards only."""
    modules = _bench_modules()
    path = modules[module]
    mine = _layer(module)
    eager = {n for n in imports_of(path, lazy=False) if n in modules}
    every = {n for n in imports_of(path) if n in modules}
    if mine > 0:
        assert every <= eager, f"{module} imports {sorted(every - eager)} inside a function"
    upward = sorted(n for n in every if _layer(n) < mine)
    assert not upward, f"{module} (layer {mine}) imports {upward} from a layer above"


def test_layer_check_catches_an_upward_import(tmp_path):
    assert _layer("bench.jobs.paper") == 2 and _layer("bench.config.scenario") == 4
    assert _layer("bench.outputs.report") < _layer("bench.jobs.single")


#: The jobs of several modules (any other module of ``bench.jobs`` is a job of its own).
#: ``uscal run`` is one job: one acquisition (``single``) or, with two datasets or more,
#: the paper's experiment (``paper``, its datasets and metrics, the re-calibration and
#: Table III); ``uscal plan`` checks a plan or, with ``--optimize``, chooses one.
BENCH_JOBS = {
    # targets: `uscal calibrate` of an N-wire or single-wire dataset, which `uscal run`
    # of a wire or cone scenario also runs on the twin's acquisition.
    "run": (
        "single",
        "paper",
        "paper_dataset",
        "paper_metrics",
        "recalibration",
        "table3",
        "targets",
    ),
    "plan": ("plan", "plan_optimize"),
}


def _job(module: str) -> str:
    name = module.removeprefix("bench.jobs.")
    return next((job for job, names in BENCH_JOBS.items() if name in names), name)


@pytest.mark.parametrize(
    "module", sorted(m for m in _bench_modules() if m.startswith("bench.jobs."))
)
def test_a_job_imports_no_other_job(module):
    """A job's modules import no module of another job: what jobs share sits below them
    (the grid executor of sweeps and budgets, :mod:`bench.grid`), and a job that runs
    another's work is handed it (``uscal budget`` runs what ``uscal run`` runs)."""
    modules = _bench_modules()
    jobs = {n for n in imports_of(modules[module]) if n.startswith("bench.jobs.") and n in modules}
    other = sorted(n for n in jobs if _job(n) != _job(module))
    assert not other, f"{module} (job {_job(module)}) imports {other} of another job"


def test_the_method_is_importable_from_calib():
    """``calib.<name>`` is the defining module's object for every public name; the shared
    maths alone does not load the localizer (lazy exports)."""
    import importlib
    import subprocess
    import sys

    import calib

    for name in calib.__all__:
        module = importlib.import_module(f"calib.{calib._EXPORTS[name]}")
        assert getattr(calib, name) is getattr(module, name)
    with pytest.raises(AttributeError):
        _ = calib.no_such_name
    code = "import sys, calib.se3; print('calib.localize' in sys.modules, 'numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.stdout.split() == ["False", "False"], out.stderr


def test_drawing_a_figure_does_not_load_the_twin():
    """``bench.outputs.figures`` draws from results: importing it loads neither MuJoCo nor the
    twin (the reconstruction's type is imported for annotations only)."""
    import subprocess
    import sys

    code = (
        "import sys, bench.outputs.figures; "
        "print(any(m in sys.modules for m in ('mujoco', 'twin', 'bench.jobs.table3')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.stdout.strip() == "False", out.stderr


def _public_definitions(path: Path) -> tuple[set[str] | None, set[str]]:
    """A module's literal ``__all__`` (None: none, or not a literal) and the public
    classes and functions it defines at the top level."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    listed = None
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            getattr(t, "id", None) == "__all__" for t in node.targets
        ):
            with contextlib.suppress(ValueError):
                listed = set(ast.literal_eval(node.value))
    defined = {
        n.name
        for n in tree.body
        if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and not n.name.startswith("_")
    }
    return listed, defined


@pytest.mark.parametrize(
    "path",
    [p for pkg in ("calib", "sim_us", "twin", "hw") for p in sorted((ROOT / pkg).rglob("*.py"))],
    ids=lambda p: p.relative_to(ROOT).as_posix(),
)
def test_every_public_definition_is_listed_in_all(path):
    """A module's ``__all__`` lists every public class and function it defines (what a
    reader takes for its API; e.g. an error class left out of ``calib.errors.__all__``)."""
    listed, defined = _public_definitions(path)
    if listed is None:
        return
    assert defined <= listed, f"not in __all__: {sorted(defined - listed)}"


def test_the_command_line_loads_a_command_s_modules_only_when_it_runs():
    """``uscal --help`` and a mistyped option answer at once: importing the command line
    loads neither the simulator, the twin, the calibration nor the recorder."""
    code = (
        "import sys, bench.cli; "
        "print(sorted(m for m in ('sim_us', 'twin', 'calib.localize', 'rerun', 'matplotlib', "
        "'scipy') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout


def test_a_run_loads_neither_scipy_stats_nor_scipy_signal():
    """What a run imports (``bench.jobs.single``: the twin, the simulator, the pipeline)
    leaves out scipy.stats and scipy.signal, ≈ 1 s of every process's start between them:
    the distribution functions come from scipy.special, the analytic signal from
    scipy.fft."""
    code = (
        "import sys, bench.jobs.single, bench.jobs.paper; "
        "print(sorted(m for m in ('scipy.stats', 'scipy.signal') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
