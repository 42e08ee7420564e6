"""The package's layout contracts (docs/design.md): no import cycles between torchhys modules
(function-level imports included), files of at most 500 lines, operators in
``torchhys/operators/``, and ``import torchhys`` without the training side."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import torchhys
from torchhys.registry import OPERATORS, load_entry_points

PACKAGE = Path(torchhys.__file__).parent
MAX_LINES = 500


def modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the torchhys modules it imports anywhere in its source (an imported name
    that is not a module counts as its module)."""
    mods = modules()

    def owner(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for module, path in mods.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for target in targets:
                found = owner(target) if target.startswith("torchhys") else None
                if found and found != module:
                    graph[module].add(found)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_between_torchhys_modules() -> None:
    graph = import_graph()
    assert sum(map(len, graph.values())) > 100  # the graph was read
    assert "torchhys.operator" in graph["torchhys.operators.preisach"]
    assert cycles(graph) == []


def test_no_file_in_the_package_over_500_lines() -> None:
    long = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def registered_names(source: str) -> list[str]:
    """The names that ``source`` registers with ``register_operator("name", ...)`` (by name
    or as an attribute; a name that is not a string constant counts as ``"?"``)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and (
                getattr(node.func, "id", None) or getattr(node.func, "attr", None)
        ) == "register_operator":
            first = node.args[0] if node.args else None
            out.append(first.value if isinstance(first, ast.Constant) else "?")
    return out


def test_the_registration_finder_finds_every_call() -> None:
    source = ("from torchhys.registry import register_operator\nimport torchhys.registry as r\n"
              "register_operator('a', A)\nr.register_operator('b', B, example=None)\n"
              "def f(name):\n    register_operator(name, C)\n")
    assert registered_names(source) == ["a", "b", "?"]


def test_the_registered_operators_live_in_their_roles_folders() -> None:
    """Every built-in operator is registered from torchhys/operators/ (the linear blocks of
    torchhys/dynamics/ by operators/linear.py), and its class lives in torchhys/operators/
    or, for a linear block, torchhys/dynamics/."""
    load_entry_points()
    builtin = {n: f for n, f in OPERATORS.items() if f.__module__.startswith("torchhys.")}
    assert len(builtin) >= 16
    found = {m: names for m, p in modules().items() if (names := registered_names(p.read_text()))}
    found.pop("torchhys.registry")  # load_entry_points: the installed packages' operators
    assert sorted(m for m in found if not m.startswith("torchhys.operators.")) == []
    assert sorted(n for names in found.values() for n in names) == sorted(builtin)
    homes = ("torchhys.operators.", "torchhys.dynamics.")
    elsewhere = {n: f.__module__ for n, f in builtin.items()
                 if not f.__module__.startswith(homes)}
    assert elsewhere == {}
    assert sum(f.__module__.startswith("torchhys.operators.") for f in builtin.values()) >= 14


def registered_families(source: str) -> dict[str, str]:
    """The families that ``source`` registers with ``register_family("name", builder)``: name
    -> the builder's name (``"?"`` for a name that is not a string constant, a builder that
    is not a plain name)."""
    out = {}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and (
                getattr(node.func, "id", None) or getattr(node.func, "attr", None)
        ) == "register_family":
            name, builder = [*node.args, None, None][:2]
            out[name.value if isinstance(name, ast.Constant) else "?"] = (
                builder.id if isinstance(builder, ast.Name) else "?")
    return out


def family_builders(source: str) -> list[str]:
    """The top-level functions of ``source`` that build a model family: one argument,
    ``spec``, and a return annotation that names ``Fitter``."""
    return sorted(node.name for node in ast.parse(source).body
                  if isinstance(node, ast.FunctionDef)
                  and [a.arg for a in node.args.args] == ["spec"]
                  and node.returns is not None and "Fitter" in ast.unparse(node.returns))


def test_the_family_finders_find_every_call_and_builder() -> None:
    source = ("from torchhys.registry import register_family\nimport torchhys.registry as r\n"
              "def _a(spec: Mapping) -> tuple[nn.Module, Fitter]: ...\n"
              "def _b(spec, other) -> Fitter: ...\n"
              "def helper(spec) -> int: ...\n"
              "register_family('a', _a)\nr.register_family('b', lambda spec: None)\n")
    assert registered_families(source) == {"a": "_a", "b": "?"}
    assert family_builders(source) == ["_a"]


def test_every_model_family_is_registered_beside_its_fit() -> None:
    """Every built-in family of ``torchhys.registry.FAMILIES`` is registered by the module of
    its builder, a family module of torchhys/identification/, and every module that defines
    a family builder registers it there."""
    from torchhys.identification import specs  # loads the family modules
    from torchhys.registry import FAMILIES

    builtin = {n: b for n, b in FAMILIES.items() if b.__module__.startswith("torchhys.")}
    assert len(builtin) >= 8
    registered, defined = {}, {}
    for m, p in modules().items():
        source = p.read_text()
        for name, builder in registered_families(source).items():
            registered[name] = (m, builder)
        if builders := family_builders(source):
            defined[m] = builders
    assert {n: (b.__module__, b.__name__) for n, b in builtin.items()} == registered
    assert {m: sorted(b for mm, b in registered.values() if mm == m) for m in defined} == defined
    shared = ("torchhys.identification._family_spec", specs.__name__)
    homes = {m for m, _ in registered.values()}
    assert all(m.startswith("torchhys.identification.") and m not in shared for m in homes)
    assert sorted(m.rpartition(".")[2] for m in homes) == sorted(
        mod.__name__.rpartition(".")[2] for mod in specs._FAMILY_MODULES)


def test_import_torchhys_imports_no_lightning() -> None:
    """``import torchhys``, the C generator, a family's fit and model selection load none of
    the train extra's packages."""
    code = ("import sys, torchhys, torchhys.deploy.c, torchhys.identification.preisach\n"
            "import torchhys.selection, torchhys.selection.run\n"
            "bad = [m for m in ('lightning', 'pytorch_lightning', 'jsonargparse', "
            "'torchmetrics', 'matplotlib') if m in sys.modules]\n"
            "assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_the_c_generator_needs_nothing_from_the_package_face(tmp_path: Path) -> None:
    """torchhys.deploy.c runs, and writes the version, with an empty ``torchhys/__init__``:
    the exporters take ``__version__`` from torchhys._version, not from the top level."""
    code = (
        "import sys, types, pathlib, torch\n"
        f"pkg = types.ModuleType('torchhys'); pkg.__path__ = [{str(PACKAGE)!r}]\n"
        "sys.modules['torchhys'] = pkg\n"
        "from torchhys._version import __version__\n"
        "from torchhys.deploy.c import to_c\n"
        "from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii as PI\n"
        "from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskiiInverse as Inv\n"
        "pi = PI(torch.tensor([0.2, 0.6]), torch.tensor([0.5, 0.3]), linear_weight=1.0)\n"
        f"header, _ = to_c(Inv(pi), {str(tmp_path)!r}, limits=(-3.0, 3.0))\n"
        "assert f'Generated by torchhys {__version__} ' in header.read_text()\n"
        "assert not [k for k in vars(pkg) if k[0].isupper() or k == '__version__']\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


TRAINING_PACKAGES = ("lightning", "pytorch_lightning", "lightning_fabric", "jsonargparse",
                     "torchmetrics", "matplotlib")
NO_TRAINING = (f"import sys\nfor name in {TRAINING_PACKAGES!r}:\n"
               "    sys.modules[name] = None  # an import of it fails\n")
"""A prelude that makes the training packages impossible to import."""


def test_torchhys_export_runs_without_lightning(tmp_path: Path) -> None:
    """``torchhys export`` reads a checkpoint as a spec plus weights: no Lightning (nor
    jsonargparse, torchmetrics, matplotlib) is imported."""
    import torch

    from torchhys import InverseHysteresisNet

    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", 4, operator_kwargs={"a": 1.3})
    x = 3 * torch.sin(torch.linspace(0, 20, 400, dtype=torch.float64))
    net = net.double()
    net.fit_normalization(x, 0.5 * x)
    hp = {"operator": "eiho", "hidden": 4, "activation": "sigmoid",
          "operator_kwargs": {"a": 1.3}}
    torch.save({"state_dict": {f"net.{k}": v for k, v in net.state_dict().items()},
                "hyper_parameters": hp}, tmp_path / "m.ckpt")
    out = tmp_path / "m.pt"
    code = NO_TRAINING + (
        "from torchhys.cli.main import main\n"
        "try:\n"
        f"    main(['export', '--ckpt', {str(tmp_path / 'm.ckpt')!r}, '--format', "
        f"'torchscript', '--out', {str(out)!r}, '--limits', '-2', '2'])\n"
        "except SystemExit as exc:\n"
        "    assert exc.code == 0, exc.code\n"
        "loaded = [m for m in sys.modules if m.split('.')[0] in "
        f"{TRAINING_PACKAGES!r} and sys.modules[m] is not None]\n"
        "assert not loaded, loaded\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stdout and out.is_file()


def test_the_data_package_imports_no_lightning() -> None:
    """Reading the data (files, tables, splits, the tensors fits read) needs no Lightning."""
    code = NO_TRAINING + (
        "import torchhys.data, torchhys.data.files, torchhys.data.tables\n"
        "import torchhys.data.splits, torchhys.data.tensors, torchhys.data.simulations\n"
        "from torchhys.data.files import read_recordings\n"
        "from torchhys.data.tensors import stack_sequences\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def _private(module: str) -> bool:
    return any(part.startswith("_") and not part.startswith("__")
               for part in module.split("."))


def test_the_top_level_names_resolve_each_from_its_one_home() -> None:
    """Every name of ``torchhys.__all__`` resolves and ``dir`` lists it; a module is there by
    its own name (no second name for a sub-submodule, as ``torchhys.export`` was); a class or
    function is defined in a public module; a name that is not there is an AttributeError."""
    import types

    import pytest

    assert len(torchhys.__all__) == len(set(torchhys.__all__))
    assert set(torchhys.__all__) <= set(dir(torchhys))
    for name in torchhys.__all__:
        value = getattr(torchhys, name)
        if isinstance(value, types.ModuleType):
            assert value.__name__ == f"torchhys.{name}", (name, value.__name__)
        elif name != "__version__":
            assert value.__name__ == name, name
            assert value.__module__.startswith("torchhys."), (name, value.__module__)
            assert not _private(value.__module__), (name, value.__module__)
    for alias in ("export", "streaming", "fitting"):
        assert alias not in torchhys.__all__
        with pytest.raises(AttributeError, match=f"has no attribute '{alias}'"):
            getattr(torchhys, alias)
    with pytest.raises(AttributeError, match="has no attribute 'Backlsh'"):
        torchhys.Backlsh  # noqa: B018


def test_a_name_loaded_on_first_use_is_its_homes_object() -> None:
    code = ("import sys, torchhys\n"
            "assert 'torchhys.identification.preisach' not in sys.modules\n"
            "assert 'torchhys.plants' not in sys.modules\n"
            "from torchhys.identification.preisach import fit_preisach\n"
            "assert torchhys.fit_preisach is fit_preisach\n"
            "assert torchhys.plants.BoucWen.__module__ == 'torchhys.plants.bouc_wen'\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_private_modules_define_no_all_and_public_alls_hold_no_private_names() -> None:
    bad = []
    for name, path in modules().items():
        for node in ast.parse(path.read_text()).body:
            targets = node.targets if isinstance(node, ast.Assign) else [
                getattr(node, "target", None)]
            if not any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                continue
            if _private(name):
                bad.append(f"{name} defines __all__")
            elif node.value is not None:
                bad += [f"{name}.__all__ holds {n}" for n in ast.literal_eval(node.value)
                        if _private(n)]
    assert bad == []


def second_paths(module: str, package: bool, source: str) -> list[str]:
    """The names of ``module``'s ``__all__`` that it imports from another torchhys module
    that is not inside it: a second public path for a name whose home is elsewhere. The
    top-level face ``torchhys`` and a package that lists its own submodules' names are one
    home and its package, not a second path."""
    base = module if package else module.rpartition(".")[0]
    tree = ast.parse(source)
    origin: dict[str, str] = {}
    names: list[str] = []
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            src = node.module or ""
            if node.level:
                up = base.split(".")[:len(base.split(".")) - node.level + 1]
                src = ".".join(up + ([src] if src else []))
            for alias in node.names:
                origin[alias.asname or alias.name] = src
        elif isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            names = ast.literal_eval(node.value)
    if module == "torchhys":
        return []
    return [f"{module}.{n} (from {origin[n]})" for n in names
            if origin.get(n, "").startswith("torchhys")
            and not (package and origin[n].startswith(f"{module}."))]


def test_the_second_path_finder_finds_a_name_from_elsewhere() -> None:
    source = ("from torchhys.a.b import X, Y as Z\nfrom .c import W\nfrom torchhys.q import V\n"
              "__all__ = ['V', 'W', 'X', 'Z']\n")
    assert second_paths("torchhys.a", True, source) == ["torchhys.a.V (from torchhys.q)"]
    assert second_paths("torchhys.a.m", False, source) == [
        "torchhys.a.m.V (from torchhys.q)", "torchhys.a.m.W (from torchhys.a.c)",
        "torchhys.a.m.X (from torchhys.a.b)", "torchhys.a.m.Z (from torchhys.a.b)"]


def test_every_public_name_has_one_public_path() -> None:
    """No public module lists in its ``__all__`` a name whose home is a module outside it
    (``torchhys.models.DuhemHysteresis`` was a second path to the operator's): beside the
    top-level face, a name is listed by its home and the packages above it only."""
    bad = [entry for name, path in modules().items() if not _private(name)
           for entry in second_paths(name, path.name == "__init__.py", path.read_text())]
    assert bad == []


def test_an_earlier_path_warns_and_names_the_home() -> None:
    """The earlier public paths of names that moved still give the same object, with a
    DeprecationWarning that names the one home; a name that never was there is an
    AttributeError."""
    import importlib

    import pytest

    moved = {"torchhys.models": {"DuhemHysteresis": "torchhys.operators.duhem",
                                 "PlayHysteresis": "torchhys.operators.play_hysteresis"},
             "torchhys.deploy.export_c": {"to_c": "torchhys.deploy.c",
                                          "check_prefix": "torchhys.deploy.c",
                                          "DEFAULT_PREFIX": "torchhys.deploy.c"},
             "torchhys.deploy.streaming": dict.fromkeys(
                 ("DIRECTIONS", "MIN_TREND", "default_direction", "default_input_range",
                  "default_limits"), "torchhys.deploy.ranges")}
    for old, names in moved.items():
        module = importlib.import_module(old)
        for name, home in names.items():
            assert name not in getattr(module, "__all__", [])
            with pytest.warns(DeprecationWarning, match=rf"^{old}\.{name} is deprecated: "
                                                        rf"use {home}\.{name} "):
                value = getattr(module, name)
            assert value is getattr(importlib.import_module(home), name)
        with pytest.raises(AttributeError, match=f"module '{old}' has no attribute 'nothing'"):
            module.nothing  # noqa: B018


MAX_TORCHHYS_MODULES = 64
"""``import torchhys`` loads at most this many torchhys modules (docs/benchmarks.md)."""


def test_import_torchhys_loads_only_what_it_needs() -> None:
    """The core (the protocol, the operators, the network) and nothing the optional parts
    need: no SciPy (the plants' ODE solver), no fit, no grey-box model."""
    code = ("import sys, torchhys\n"
            "print(sum(m == 'torchhys' or m.startswith('torchhys.') for m in sys.modules))\n"
            "print(' '.join(m for m in ('scipy', 'torchdiffeq', 'torchhys.plants', "
            "'torchhys.identification', 'torchhys.models') "
            "if m in sys.modules))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    count, loaded = proc.stdout.splitlines()
    assert int(count) <= MAX_TORCHHYS_MODULES
    assert loaded == ""


def test_make_reproduce_runs_the_reproduction_package() -> None:
    """``make reproduce`` runs ``python -m torchhys.reproduce`` (its own package, beside the
    training side), whose usage names that command."""
    root = PACKAGE.parent
    recipe = (root / "Makefile").read_text().split("\nreproduce:", 1)[1].split("\n\n")[0]
    module = recipe.split(" -m ", 1)[1].split()[0]
    assert module == "torchhys.reproduce"
    proc = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True,
                          text=True, cwd=root)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"usage: python -m {module} "), proc.stdout[:80]


def test_the_top_level_lists_what_the_readmes_api_table_lists() -> None:
    """Every ``torchhys.<name>`` of the README's API table is a top-level name (but
    ``torchhys.training``, which needs the ``train`` extra and is reached by its own import),
    and every top-level name is in the table."""
    import re

    text = (PACKAGE.parent / "README.md").read_text()
    api = text[text.index("\n## API\n"):]
    api = api[:api.index("\n## ", 1)]
    named = {m.group(1) for m in re.finditer(r"(?<![\w.])torchhys\.(\w+)", api)}
    assert named - set(torchhys.__all__) == {"training"}
    unlisted = [n for n in torchhys.__all__
                if n != "__version__" and not re.search(rf"(?<!\w){n}(?!\w)", api)]
    assert unlisted == []
