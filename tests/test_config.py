from pathlib import Path

import pytest
import yaml

from parammap.config import ConfigError, load_config, validate_config

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_config_is_valid_and_defaults_fill():
    cfg = load_config(ROOT / "config" / "config.yaml")
    assert cfg["captures"] == {"demo": "data/captures/demo"}
    assert cfg["hdr"]["method"] == "debevec"
    assert validate_config({"captures": {"a": "x"}})["poses"]["max_rms_px"] == 2.0


@pytest.mark.parametrize(
    "cfg, key",
    [
        ({"captures": {"a": "x"}, "hdr": {"samples": 3}}, "hdr.samples"),
        ({"captures": {"a": "x"}, "hdr": {"method": "magic"}}, "hdr.method"),
        ({"captures": {}}, "captures"),
        ({"captures": {"a": "x"}, "workers": 0}, "workers"),
        ({"captures": {"a": "x"}, "typo_key": 1}, "<top>"),
        ({"captures": {"a": "x"}, "synth": {"a": {"preset": "huge"}}}, "synth.a.preset"),
    ],
)
def test_bad_values_name_the_key(cfg, key):
    with pytest.raises(ConfigError, match=f"config: {key}"):
        validate_config(cfg)


def test_schema_file_is_shared_with_workflow():
    wf = ROOT / "workflow" / "schemas" / "config.schema.yaml"
    pkg = ROOT / "src" / "parammap" / "schemas" / "config.schema.yaml"
    assert wf.resolve() == pkg.resolve()


def test_surface_overrides_merge_and_name_bad_keys():
    from parammap.config import surface_config

    cfg = validate_config({"captures": {"a": "x", "b": "y"},
                           "overrides": {"a": {"observation": {"texels_x": 64}}}})
    assert cfg["observation"]["texels_x"] == "auto"
    assert surface_config(cfg, "a")["observation"]["texels_x"] == 64
    assert surface_config(cfg, "a")["observation"]["tile"] == 32
    assert surface_config(cfg, "b")["observation"]["texels_x"] == "auto"
    bad = validate_config({"captures": {"a": "x"},
                           "overrides": {"a": {"observation": {"texels_x": "big"}}}})
    with pytest.raises(ConfigError, match=r"observation.texels_x.*overrides.a"):
        surface_config(bad, "a")


def test_auto_map_resolution_and_budget():
    from types import SimpleNamespace

    from parammap.stages.poses import map_resolution
    from parammap.stores.observation import BYTES_PER_OBSERVATION

    cap = SimpleNamespace(width_mm=200.0, height_mm=100.0)
    g = map_resolution(cap, [1.5, 2.0, 2.5], 50, "auto", None, 4.0)
    assert (g["S"], g["T"], g["source"]) == (400, 200, "auto") and not g["capped_by_budget"]
    small = 400 * 200 * 50 * BYTES_PER_OBSERVATION / 4 / 2**30
    g = map_resolution(cap, [1.5, 2.0, 2.5], 50, "auto", None, small)
    assert g["capped_by_budget"] and abs(g["S"] - 200) <= 1 and abs(g["T"] - 100) <= 1
    g = map_resolution(cap, [2.0], 50, 64, None, 4.0)
    assert (g["S"], g["T"], g["source"]) == (64, 32, "config")


def test_numbers_given_as_text_are_read_as_numbers():
    # Snakemake's --config hands nested values over as strings
    # (observation={"texels_x": 512} arrives as '512')
    cfg = validate_config({"captures": {"x": "."},
                           "observation": {"texels_x": "512", "max_map_gib": "2.5"},
                           "fit": {"mh": {"lobes": ["1", "auto"]}},
                           "materials": {"enabled": "false"}})
    assert cfg["observation"]["texels_x"] == 512
    assert cfg["observation"]["max_map_gib"] == 2.5
    assert cfg["fit"]["mh"]["lobes"] == [1, "auto"]
    assert cfg["materials"]["enabled"] is False
    with pytest.raises(ConfigError, match="observation.texels_x"):
        validate_config({"captures": {"x": "."}, "observation": {"texels_x": "many"}})


@pytest.mark.parametrize("snakemake, override", [(None, None), ("2", None), ("2", "2")])
def test_the_command_line_runs_blas_on_one_thread_unless_told(monkeypatch, snakemake,
                                                               override):
    """The stages are parallel over views and tiles: the command line sets one BLAS
    thread for itself and its workers, also where Snakemake set OMP_NUM_THREADS and its
    kin to the job's threads (which the stages spend on worker processes); only
    PARAMMAP_BLAS_THREADS asks for more."""
    import os

    from threadpoolctl import threadpool_info, threadpool_limits

    from parammap.cli import BLAS_THREAD_VARIABLES, BLAS_THREADS_OVERRIDE, main

    for v in (*BLAS_THREAD_VARIABLES, BLAS_THREADS_OVERRIDE):
        monkeypatch.delenv(v, raising=False)
    for v in BLAS_THREAD_VARIABLES if snakemake else ():
        monkeypatch.setenv(v, snakemake)
    if override:
        monkeypatch.setenv(BLAS_THREADS_OVERRIDE, override)
    want = int(override or 1)
    with threadpool_limits(3, user_api="blas"):
        with pytest.raises(SystemExit):
            main(["--version"])
        threads = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
        assert all(os.environ[v] == str(want) for v in BLAS_THREAD_VARIABLES)
        assert threads == {want}


def _schema_defaults() -> dict[str, list[tuple[str, object]]]:
    """Leaf name -> (dotted key, default) of every scalar default in the schema."""
    from parammap.config import schema

    leaves: dict[str, list[tuple[str, object]]] = {}

    def walk(node: dict, path: list[str]) -> None:
        for key, sub in (node.get("properties") or {}).items():
            if "default" in sub and not isinstance(sub["default"], dict | list):
                leaves.setdefault(key, []).append((".".join(path + [key]), sub["default"]))
            walk(sub, path + [key])

    walk(schema(), [])
    return leaves


def test_every_config_default_is_written_once_in_the_schema():
    """No Python default (a parameter, a dataclass field, a constant) repeats a schema
    default under the setting's name: it reads :func:`parammap.config.default`. Seeds
    are left out: a function's ``seed=0`` is its own reproducible stream, not the
    config's."""
    import ast

    leaves = _schema_defaults()
    assert leaves["low"] == [("hdr.low", 5)]  # the walk reads the schema
    found = []
    for path in sorted((ROOT / "src" / "parammap").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            pairs = []
            if isinstance(node, ast.FunctionDef):
                a = node.args
                pos = a.posonlyargs + a.args
                pairs += list(zip((x.arg for x in pos[len(pos) - len(a.defaults):]),
                                  a.defaults, strict=True))
                pairs += [(x.arg, d) for x, d in zip(a.kwonlyargs, a.kw_defaults, strict=True)
                          if d is not None]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                pairs.append((node.target.id, node.value))
            for name, value in pairs:
                if name == "seed" or not isinstance(value, ast.Constant) or value.value is None:
                    continue
                for key, d in leaves.get(name, []):
                    if type(value.value) is type(d) and value.value == d:
                        found.append(f"{path.name}:{node.lineno} {name}={d!r} ({key})")
    assert not found, "\n".join(found)


def test_shipped_config_holds_only_what_users_change():
    """``config/config.yaml`` is short and restates no default: what it sets differs
    from the schema's default, or is a section the schema has none for."""
    from parammap.config import default

    text = (ROOT / "config" / "config.yaml").read_text()
    assert len(text.splitlines()) < 40
    cfg = yaml.safe_load(text)

    def walk(node: dict, path: list[str]) -> list[str]:
        same = []
        for key, value in node.items():
            full = ".".join(path + [key])
            if isinstance(value, dict) and path[:1] not in (["captures"], ["synth"],
                                                          ["overrides"]):
                same += walk(value, path + [key])
            else:
                try:
                    if default(full) == value:
                        same.append(full)
                except KeyError:
                    pass
        return same

    assert not walk(cfg, [])


def test_long_steps_say_how_far_they_got(caplog):
    """Progress of a long step: a log line at every tenth and at the end where nobody
    watches a terminal (a resumed step counts what was done before); a bar redrawn in
    place on a terminal."""
    import io
    import logging

    from parammap.parallel import progress

    log = logging.getLogger("parammap.test_progress")
    with caplog.at_level(logging.INFO, logger=log.name):
        assert list(progress(range(20), 20, "step:", log, done=5, of=25)) == list(range(20))
    lines = [r.getMessage() for r in caplog.records if r.name == log.name]
    assert lines == [f"step: {5 + k}/25" for k in range(2, 21, 2)]

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    log.setLevel(logging.INFO)
    assert list(progress(iter("abc"), 3, "step:", log, stream=term)) == ["a", "b", "c"]
    out = term.getvalue()
    assert out.count("\r") == 3 and out.endswith("3/3\n") and "#" * 30 in out


def test_a_map_coarser_than_the_photos_says_so(tiny_processed, tmp_path, caplog):
    """Issue 47: where the budget caps the auto map, the map records the photos' own
    resolution and the poses stage warns, naming the setting to raise."""
    import logging
    import shutil
    from types import SimpleNamespace

    from parammap.stages.poses import map_resolution, run_poses
    from parammap.stores.capture import load_capture
    from parammap.stores.common import free_disk_gib

    cap = SimpleNamespace(width_mm=200.0, height_mm=100.0)
    g = map_resolution(cap, [2.0], 50, "auto", None, 1e-3)
    assert g["capped_by_budget"] and (g["photos_S"], g["photos_T"]) == (400, 200)
    assert g["photos_map_gib"] > 1e-3 and g["S"] < 400

    capture, _, processed = tiny_processed
    work = tmp_path / "proc"
    shutil.copytree(processed, work)
    cfg = validate_config({"captures": {"x": "."}, "observation": {"max_map_gib": 1e-6}})
    with caplog.at_level(logging.INFO, logger="parammap"):
        m = run_poses(load_capture(capture), work, cfg, workers=1)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING
              and "max_map_gib" in r.getMessage()]
    assert m["map"]["capped_by_budget"] and len(warned) == 1, (m["map"], warned)
    # unset, the budget is the disk's: half its free space, said in the log
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="parammap"):
        m = run_poses(load_capture(capture), work, validate_config({"captures": {"x": "."}}),
                      workers=1)
    said = [r.getMessage() for r in caplog.records if "free on" in r.getMessage()]
    assert len(said) == 1 and not m["map"]["capped_by_budget"], said
    assert m["map"]["max_map_gib"] == pytest.approx(free_disk_gib(work) / 2, rel=0.05)


def test_captures_named_on_the_command_line_are_the_runs_only_ones(tiny_capture, tmp_path):
    """``snakemake --config 'captures={...}'`` (the README's command) runs those surfaces
    alone: Snakemake merges the mapping into the config file's, which added the
    built-in demo (and its generation) to every lab's run."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    cap, _ = tiny_capture
    (tmp_path / "config").mkdir()
    shutil.copy(root / "config" / "config.yaml", tmp_path / "config" / "config.yaml")
    r = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(root / "Snakefile"), "--directory",
         str(tmp_path), "--cores", "1", "--dry-run", "--printshellcmds", "--config",
         f'captures={{"lab1": "{cap}"}}'], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "synth" not in r.stdout and "demo" not in r.stdout, r.stdout[-3000:]
    assert f"validate-capture {cap}" in r.stdout
