"""The package's layout is its pipeline: each stage imports only from stages below it, and nothing imports in a
cycle. Read from the source with ``ast``, lazy imports inside functions included."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# stage -> rank; a module may import from its own stage and from lower ranks only
LAYERS = ["common", "mesh", "ground_truth", "dataset", "model", "training", "inference", "evaluation", "pictures",
          "generalizable", "cli"]
KERNEL_LAYERS = {"mesh": "mesh", "ground_truth": "ground_truth", "inference": "inference", "field": "inference",
                 "pictures": "pictures", "generalizable": "generalizable"}


def _modules():
    """{dotted module name: path} of neurogf_warp and neurogf_warp.kernels (installed from kernels/)."""
    mods = {}
    for top, folder in (("neurogf_warp", ROOT / "neurogf_warp"), ("neurogf_warp.kernels", ROOT / "kernels")):
        for f in folder.rglob("*.py"):
            parts = list(f.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join([top, *parts])] = f
    return mods


def _stage(module: str):
    """The pipeline stage of a dotted module name (None for the package's top level)."""
    parts = module.split(".")
    if parts[:2] == ["neurogf_warp", "kernels"]:
        return KERNEL_LAYERS.get(parts[2]) if len(parts) > 2 else None
    return parts[1] if len(parts) > 1 else None


def _imports(module: str, path: Path):
    """Dotted names of the neurogf_warp modules that ``module`` imports (absolute and relative forms)."""
    tree = ast.parse(path.read_text())
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.startswith("neurogf_warp"))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            if base.startswith("neurogf_warp"):
                yield base
                for a in node.names:  # `from neurogf_warp.x import y` where y is a module
                    yield f"{base}.{a.name}"


def _graph():
    mods = _modules()
    return mods, {m: {i for i in _imports(m, p) if i in mods and i != m} for m, p in mods.items()}


def test_every_module_belongs_to_a_stage():
    mods, _ = _graph()
    loose = [m for m in mods if m.count(".") >= 1 and _stage(m) is None and m != "neurogf_warp.kernels"]
    unknown = [m for m in mods if _stage(m) is not None and _stage(m) not in LAYERS]
    assert not loose and not unknown, (loose, unknown)


def test_no_import_from_a_higher_stage():
    _, graph = _graph()
    upward = [f"{m} -> {i}" for m, deps in graph.items() for i in deps
              if _stage(m) is not None and _stage(i) is not None
              and LAYERS.index(_stage(i)) > LAYERS.index(_stage(m))]
    assert not upward, "imports from a higher stage of the pipeline:\n" + "\n".join(sorted(upward))


def test_no_import_cycles():
    _, graph = _graph()
    # the package roots only re-export (lazily, by name); leave them out so that a cycle is between modules
    graph = {m: {i for i in d if i not in ("neurogf_warp", "neurogf_warp.training")} for m, d in graph.items()}
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for i in sorted(graph.get(m, ())):
            if state.get(i) == 1:
                cycles.append(" -> ".join(stack[stack.index(i):] + [i]))
            elif i not in state:
                visit(i)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)
