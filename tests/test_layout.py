"""The package's layout holds: stages side by side over the stores and the models, no
import circle, every package import at the top of its module (read with ``ast``)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "src" / "parammap"

# Floors from the bottom: a module may import only from its own floor's shared modules
# and from floors below. Stages are one floor: none imports another.
STAGES = "parammap.stages"
BELOW_STAGES = ("parammap.stores", "parammap.models", "parammap.vision",
                "parammap.conventions", "parammap.errors", "parammap.geometry",
                "parammap.config", "parammap.parallel", "parammap.plots",
                "parammap.render")
# the store layer and the pure numerics never reach up into a stage or an application
LOWER = ("parammap.stores", "parammap.models", "parammap.conventions",
         "parammap.errors", "parammap.geometry", "parammap.parallel", "parammap.vision")
UPPER = ("parammap.stages", "parammap.cli", "parammap.paper", "parammap.viewer", "parammap.sheets",
         "parammap.synth", "parammap.compare")


def _module(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, bool]]:
    """(imported parammap module, at the module's top level) for each import."""
    mod = _module(path)
    base = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                here = base[: len(base) - node.level + 1]
                target = ".".join(here + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("parammap"):
                continue
            for alias in node.names:  # "from . import x" may name a module
                sub = f"{target}.{alias.name}"
                full = sub if (PKG.parent / (sub.replace(".", "/") + ".py")).exists() \
                    or (PKG.parent / sub.replace(".", "/")).is_dir() else target
                out.append((full, id(node) in top))
        elif isinstance(node, ast.Import):
            out += [(a.name, id(node) in top) for a in node.names
                    if a.name.startswith("parammap")]
    return out


MODULES = {_module(p): p for p in sorted(PKG.rglob("*.py"))}


def _within(mod: str, prefixes: tuple[str, ...] | str) -> bool:
    prefixes = (prefixes,) if isinstance(prefixes, str) else prefixes
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def test_no_stage_imports_another_stage():
    bad = [f"{mod} imports {target}" for mod, path in MODULES.items()
           if _within(mod, STAGES) for target, _ in _imports(path)
           if _within(target, STAGES) and target != STAGES]
    assert not bad, "\n".join(bad)


def test_stages_import_only_what_lies_below_them():
    bad = [f"{mod} imports {target}" for mod, path in MODULES.items()
           if _within(mod, STAGES) for target, _ in _imports(path)
           if target != "parammap" and not _within(target, BELOW_STAGES)]
    assert not bad, "\n".join(bad)


def test_stores_and_models_do_not_reach_up():
    bad = [f"{mod} imports {target}" for mod, path in MODULES.items()
           if _within(mod, LOWER) for target, _ in _imports(path) if _within(target, UPPER)]
    assert not bad, "\n".join(bad)


# The command line imports the one stage a command runs, inside that command: every
# workflow rule starts a process, which should not pay for every stage's imports.
LAZY = ("parammap.cli",)


def test_package_imports_are_at_the_top_of_modules():
    bad = [f"{mod} imports {target} inside a function" for mod, path in MODULES.items()
           if mod not in LAZY for target, top in _imports(path) if not top]
    assert not bad, "\n".join(bad)


# Imported where they are used, not at the top: optional (the physically based
# generator's Mitsuba, numba's compiled kernels with numpy fallbacks, a dask cluster's
# client), or heavy and wanted by a few figures (matplotlib).
LOCAL_OK = ("mitsuba", "drjit", "numba", "matplotlib", "dask")


def test_other_imports_are_at_the_top_unless_optional_or_heavy():
    bad = []
    for mod, path in MODULES.items():
        if mod in LAZY:
            continue
        tree = ast.parse(path.read_text())
        top = {id(n) for n in tree.body}
        top |= {id(m) for n in tree.body if isinstance(n, ast.Try) for m in ast.walk(n)}
        for node in ast.walk(tree):
            if id(node) in top or not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            if isinstance(node, ast.ImportFrom) and node.level:
                continue  # package imports: the test above
            name = (node.module if isinstance(node, ast.ImportFrom) else node.names[0].name)
            if name.split(".")[0] not in LOCAL_OK + ("parammap",):
                bad.append(f"{mod}:{node.lineno} imports {name} inside a function")
    assert not bad, "\n".join(bad)


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for mod, path in MODULES.items():
        for target, _ in _imports(path):
            # importing a package runs its __init__: an edge to the package itself
            node = target if target in MODULES else target.rsplit(".", 1)[0]
            if node in MODULES and node != mod:
                graph[mod].add(node)
    return graph


def test_no_import_circle():
    graph, state, stack, circles = _graph(), {}, [], []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                circles.append(" -> ".join(stack[stack.index(n):] + [n]))
            elif n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not circles, "\n".join(circles)


@pytest.mark.parametrize("mod", ["parammap.stages.hdr", "parammap.stores.fit"])
def test_the_layout_test_reads_real_modules(mod):
    """The checks above read something: each names a module with package imports."""
    assert _imports(MODULES[mod])


# ---------------------------------------------------------------------------------
# Names on disk: the stores alone spell them


def _string_constants(path: Path) -> set[str]:
    return {n.value for n in ast.walk(ast.parse(path.read_text()))
            if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def test_only_the_stores_open_zarr_and_exr():
    """zarr and OpenEXR are imported, and EXR files read or written, by the stores alone
    (and the generic comparison of two runs, which names nothing); nothing else touches
    a store's ``attrs``."""
    bad = []
    for mod, path in MODULES.items():
        if _within(mod, "parammap.stores") or mod == "parammap.compare":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) \
                    else [node.module or ""]
                bad += [f"{mod} imports {n}" for n in names
                        if n.split(".")[0] in ("zarr", "OpenEXR", "Imath")]
            if isinstance(node, ast.Attribute) and node.attr == "attrs" \
                    and not isinstance(node.ctx, ast.Store):
                bad.append(f"{mod}:{node.lineno} reads a store's attrs")
            if isinstance(node, ast.Name) and node.id in ("read_exr", "write_exr"):
                bad.append(f"{mod}:{node.lineno} uses {node.id}")
    assert not bad, "\n".join(bad)


def _owned_names() -> dict[str, set[str]]:
    """Every zarr array and attribute name and every EXR channel name the artifacts use."""
    from parammap import conventions as cv
    from parammap.stores import hdr, observation

    arrays = {observation.RADIANCE, observation.DIRECTION, observation.VALID,
              observation.NOISE} | {str(a) for a in cv.FitArray}
    attributes = {
        # grid and provenance (observation map, fit stores, EXR headers)
        "S", "T", "tile", "width_mm", "height_mm", "software", "parammap_complete",
        # the observation map's build
        "view_ids", "held_out_view_ids", "camera_centres_mm", "calibration", "sampling",
        "marker_texels", "surface_id", "units",
        # fit stores
        "parammap_resume_key", "model", "model_version", "lobes", "K_max", "layout",
        "hemisphere", "coefficients", "sampled_cap", "solid_angles", "regularisation",
        "observation_views",
    }
    channels = set(hdr.HDR_CHANNELS) | set(cv.mh_channels(3)) | set(cv.mh_sd_channels(3)) \
        | set(cv.sh_channels(4)) | set(cv.DIFFUSE_CHANNELS) | set(cv.BEST_CHANNELS) \
        | {"parammap_model", "parammap_model_version", "parammap_layout",
           "parammap_hemisphere", "parammap_sd_layout"}
    return {"array": arrays, "attribute": attributes, "channel": channels}


# the modules that own zarr and EXR names (YAML files, paths and metrics have names of
# their own)
NAME_OWNERS = ("parammap.conventions", "parammap.stores.common", "parammap.stores.exr",
               "parammap.stores.hdr", "parammap.stores.observation", "parammap.stores.fit",
               "parammap.stores.params")


def test_every_zarr_and_exr_name_is_spelled_in_one_module():
    owned = _owned_names()
    spelled = {mod: _string_constants(MODULES[mod]) for mod in NAME_OWNERS}
    bad, seen = [], 0
    for kind, names in owned.items():
        for name in sorted(names):
            where = [mod for mod, consts in spelled.items() if name in consts]
            seen += bool(where)
            if len(where) > 1:
                bad.append(f"{kind} {name!r} spelled in {', '.join(where)}")
    assert seen > 60, "the names were not found where they are written"
    assert not bad, "\n".join(bad)


# Subscripts with these words that address something else than a store: the lobe
# plots' entries, the viewer's model description, a pose refinement's result.
NOT_A_STORE = {("parammap.plots", "direction"), ("parammap.plots", "label"),
               ("parammap.viewer.inspect", "params"), ("parammap.vision.pose", "noise")}


def test_no_stage_addresses_a_store_array_by_its_literal_name():
    """Outside the stores and conventions, no ``x["valid"]`` or ``"noise" in x`` with a
    store's array name: stages read arrays through the stores' typed readers."""
    arrays = _owned_names()["array"]
    bad = []
    for mod, path in MODULES.items():
        if _within(mod, "parammap.stores") or mod == "parammap.conventions":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            key = None
            if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
                key = node.slice.value
            elif isinstance(node, ast.Compare) and isinstance(node.left, ast.Constant) \
                    and any(isinstance(op, ast.In | ast.NotIn) for op in node.ops):
                key = node.left.value
            if key in arrays and (mod, key) not in NOT_A_STORE:
                bad.append(f"{mod}:{node.lineno} {ast.unparse(node)}")
    assert not bad, "\n".join(bad)
