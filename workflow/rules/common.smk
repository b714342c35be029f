# Shared helpers: validated config, capture paths, output folders.
import json
import re
import shlex
import sys

from parammap.config import validate_config

# Stops the run naming the bad key before any job starts.
config = validate_config(config)

CAPTURES = config["captures"]
SYNTH = config["synth"]
PROC = config["processed_dir"]
REPORTS = config["reports_dir"]
WORKERS = config["workers"]
# The interpreter running Snakemake has parammap installed; no PATH lookup needed.
PARAMMAP = f'"{sys.executable}" -m parammap'
SYNTH_DIRS_RE = "|".join(re.escape(CAPTURES[s]) for s in SYNTH if s in CAPTURES) or "$^"


wildcard_constraints:
    sid="[A-Za-z0-9][A-Za-z0-9_.-]*",


def config_arg(*sections):
    """The config sections a stage reads, passed to its CLI as JSON: the CLI sees the
    same (command-line extended) config as the workflow, and a change to one section
    reruns only the stages that read it."""
    part = {k: config[k] for k in sections} | {"workers": config["workers"]}
    return "--config-json " + shlex.quote(json.dumps(part, sort_keys=True))


def capture_dir(wildcards):
    return CAPTURES[wildcards.sid]


def view_ids(wildcards):
    """View ids of a capture, known once the capture exists and has validated."""
    checkpoints.validate_capture.get(sid=wildcards.sid)
    from parammap.capture import load_capture

    return [v.id for v in load_capture(CAPTURES[wildcards.sid]).views]


def mh_models():
    return [f"mh-{k}" for k in config["fit"]["mh"]["lobes"]]


def models():
    """Every fitted model name (outputs.md): mh-<K> and sh-<hemisphere>-<n^2>."""
    return mh_models() + list(config["fit"]["sh"]["models"])


def all_targets():
    targets = []
    for sid in CAPTURES:
        targets += [
            f"{REPORTS}/{sid}/contact_sheet.png",
            f"{PROC}/{sid}/camera/poses.yaml",
            f"{PROC}/{sid}/metrics/hdr.json",
            f"{PROC}/{sid}/metrics/observation.json",
        ]
        targets += [f"{PROC}/{sid}/metrics/fit-{m}.json" for m in models()]
    return targets


def synth_for(capdir):
    for sid, spec in SYNTH.items():
        if CAPTURES.get(sid) == capdir:
            return spec
    raise ValueError(f"no synth entry for {capdir}")


def synth_sid(capdir):
    return next(s for s in SYNTH if CAPTURES.get(s) == capdir)
