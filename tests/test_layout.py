"""The house rules, checked on the source tree: which package may import what, one numba flag set,
the public names users hold, and no file pointing outside the repository.

The import checks read every ``import`` statement of the packages with ``ast`` (module level and inside
functions alike), in the spirit of stumpy's ``check_fastmath``: a rule that is only written down drifts.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("noise_model", "elevmap")

#: Top-level names that ``noise_model`` exported before its simulator and analysis moved into
#: subpackages: users hold them as ``nm.<name>`` or ``from noise_model import <name>``.
NOISE_MODEL_NAMES = [
    "Box", "D435", "EFFECTS", "HeightField", "MapPoints", "Ramp", "Scene", "SensorModel", "Stairs",
    "THETA_MAX_DEFAULT", "THETA_QUADRATURE", "Target", "Workspace", "add_noise", "alternatives", "axial_sigma",
    "axial_variance", "check_angles", "check_covariances", "check_depth", "check_intrinsics", "check_points",
    "check_pose_cov", "check_transform", "check_transforms", "correlated_noise", "default_block_px", "deproject",
    "depth_bias", "depth_edges", "depth_to_map_points", "depth_to_map_points_reference", "depth_to_metres",
    "despeckle", "effects", "expected_rms_error", "incidence_angle_stats", "incidence_angles", "kernels",
    "mixed_windows", "odometry_drift", "point_covariances", "pose_jacobian", "render_depth",
    "render_depth_reference", "row_medians", "scene", "sim", "simulate_walk", "skew", "surface_depths",
    "to_map_frame", "walk",
]
#: The names ``elevmap`` exports: the map, the mapper, and the entry points the examples use.
ELEVMAP_NAMES = ["ElevationMap", "FusionParams", "Mapper", "Camera", "open_source", "run_mapping", "MappingConfig"]


def _sources(*roots: str):
    for root in roots:
        for path in sorted((ROOT / root).rglob("*.py")):
            yield path


def _imports(path: Path, module_level_only: bool = False) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``, relative imports resolved.

    ``from a import b`` yields both ``a`` and ``a.b`` (b may be a submodule).
    """
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    package = parts[:-1]
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in (tree.body if module_level_only else ast.walk(tree)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names]
    return out


def _offenders(top: str, allowed) -> list[str]:
    bad = []
    for path in _sources(*PACKAGES):
        rel = path.relative_to(ROOT).as_posix()
        if any(rel.startswith(a) for a in allowed):
            continue
        for line, mod in _imports(path):
            if mod == top or mod.startswith(top + "."):
                bad.append(f"{rel}:{line} imports {mod}")
    return sorted(set(bad))


@pytest.mark.parametrize("top, allowed", [
    ("elevmap", ("elevmap/",)),                                    # noise_model never imports elevmap
    ("rerun", ("elevmap/viz/", "elevmap/sources/rrd.py")),
    ("pyrealsense2", ("elevmap/sources/",)),
    ("cv2", ("elevmap/sources/", "noise_model/analysis/detection.py")),
    ("tqdm", ("elevmap/",)),                                       # progress bars belong to the commands
    ("rosbags", ("elevmap/ros/", "elevmap/sources/rosbag.py")),   # ROS messages and bags
    ("foxglove", ("elevmap/ros/",)),                               # the live Foxglove view
])
def test_each_library_is_imported_only_where_its_layer_allows(top, allowed):
    assert _offenders(top, allowed) == []


def test_the_map_core_imports_no_io_visualisation_or_simulator():
    bad = []
    for path in _sources("elevmap/map"):
        for line, mod in _imports(path):
            if re.match(r"(elevmap\.(sources|viz|commands|cli|pipeline)|noise_model\.(sim|analysis)|rerun|tqdm|"
                        r"matplotlib|cv2|pyrealsense2)(\.|$)", mod):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert bad == []


def test_the_simulator_does_not_import_the_analysis_at_load_time():
    bad = [f"{path.relative_to(ROOT)}:{line} imports {mod}" for path in _sources("noise_model/sim")
           for line, mod in _imports(path, module_level_only=True) if mod.startswith("noise_model.analysis")]
    assert sorted(set(bad)) == []


def _fresh_import(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)


def test_importing_the_map_loads_neither_simulator_nor_viewer():
    code = ("import sys, elevmap; bad = [m for m in sys.modules if m.startswith(('noise_model.sim', "
            "'noise_model.analysis', 'rerun', 'cv2', 'pyrealsense2', 'matplotlib', 'rosbags', 'foxglove', "
            "'elevmap.commands', "
            "'elevmap.viz'))]; print(bad); sys.exit(1 if bad else 0)")
    res = _fresh_import(code)
    assert res.returncode == 0, res.stdout + res.stderr


def test_every_name_users_hold_still_imports():
    code = ("import noise_model as nm, elevmap\n"
            f"missing = [n for n in {NOISE_MODEL_NAMES!r} if not hasattr(nm, n)]\n"
            f"missing += ['elevmap.' + n for n in {ELEVMAP_NAMES!r} if not hasattr(elevmap, n)]\n"
            "from noise_model import *\nfrom elevmap import *\n"
            "print(missing); raise SystemExit(1 if missing else 0)")
    res = _fresh_import(code)
    assert res.returncode == 0, res.stdout + res.stderr


def test_every_njit_takes_the_shared_flag_set():
    """Every ``njit(...)``/``jit(...)`` call passes ``**JIT`` and sets no numba flag of its own."""
    bad = []
    for path in _sources(*PACKAGES):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call):
                continue
            name = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
            if name not in ("njit", "jit"):
                continue
            spread = [k for k in node.keywords if k.arg is None]
            own = {k.arg for k in node.keywords if k.arg is not None}
            if not (spread and getattr(spread[0].value, "id", None) == "JIT") or own & {"fastmath", "cache",
                                                                                          "error_model"}:
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert bad == []


def _text_files():
    yield ROOT / "README.md"
    for root in ("docs", "elevmap", "noise_model", "examples"):
        for path in sorted((ROOT / root).rglob("*")):
            if path.suffix in (".py", ".md", ".toml", ".txt"):
                yield path


def test_no_issue_session_or_step_numbers_in_code_or_docs():
    pattern = re.compile(r"issue [0-9]|[Ss]ession [0-9]|step [0-9]+ of")
    bad = [f"{p.relative_to(ROOT)}:{k}" for p in _text_files()
           for k, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert bad == []


def test_nothing_cites_a_file_outside_the_repository():
    pattern = re.compile(r"\.\./shared|shared/(notes|specs|realdata)")
    bad = [f"{p.relative_to(ROOT)}:{k}" for p in _text_files()
           for k, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert bad == []
