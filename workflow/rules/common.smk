# Shared helpers: validated config, capture paths, output folders.
import json
import re
import shlex
import sys

from parammap.config import surface_config, validate_config

# Surfaces named on the command line (--config 'captures={...}') are the run's only
# ones: Snakemake merges a mapping given there into the config file's, which would add
# the built-in demo (and generate it) to every lab's run.
_given = workflow.config_settings.overwrite_config or {}
if "captures" in _given:
    config["captures"] = dict(_given["captures"])
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
    """The config sections a stage reads (with the surface's ``overrides``), passed to
    its CLI as JSON: the CLI sees the same (command-line extended) config as the
    workflow, and a change to one section reruns only the stages that read it."""

    def arg(wildcards):
        cfg = surface_config(config, wildcards.sid)
        part = {k: cfg[k] for k in sections} | {"workers": cfg["workers"]}
        return "--config-json " + shlex.quote(json.dumps(part, sort_keys=True))

    return arg


def capture_dir(wildcards):
    return CAPTURES[wildcards.sid]


def view_ids(wildcards):
    """View ids of a capture, known once the capture exists and has validated."""
    checkpoints.validate_capture.get(sid=wildcards.sid)
    from parammap.stores.capture import load_capture

    return [v.id for v in load_capture(CAPTURES[wildcards.sid]).views]


def radiometry_view_ids(wildcards):
    """The white card's views and the colour chart's bracket (none for most captures)."""
    checkpoints.validate_capture.get(sid=wildcards.sid)
    from parammap.stores.capture import load_capture

    return [v.id for v in load_capture(CAPTURES[wildcards.sid]).radiometry_views]


def mh_models():
    return [f"mh-{k}" for k in config["fit"]["mh"]["lobes"]]


def models():
    """Every fitted model name (outputs.md): mh-<K>, sh-<hemisphere>-<n^2> and, where
    enabled, the basis materials mh-materials and the microfacet SVBRDF svbrdf-ggx."""
    extra = ["mh-materials"] if config["materials"]["enabled"] else []
    extra += ["svbrdf-ggx"] if config["fit"]["svbrdf"]["enabled"] else []
    return mh_models() + list(config["fit"]["sh"]["models"]) + extra


def mh_source(section):
    """The MH fit a later stage builds on: the configured ``<section>.source`` when the
    workflow fits it, else the last MH model it fits (never an extra, unasked fit)."""
    want = config[section]["source"]
    fitted = mh_models()
    return want if want in fitted or not fitted else fitted[-1]


def sh_source():
    """The MH fit sh-mh-<n^2> bakes: ``fit.sh.source`` where the workflow makes it (the
    basis materials where enabled), else the last MH fit it makes."""
    want = config["fit"]["sh"]["source"]
    made = mh_models() + (["mh-materials"] if config["materials"]["enabled"] else [])
    return want if want in made or not made else mh_models()[-1]


def compared_models():
    """The maps the held-out comparison scores: every model, the best-per-texel map
    where enabled, and the diffuse baseline."""
    return models() + (["best"] if config["best"]["enabled"] else []) + ["diffuse"]


def benchmark_files(sid):
    """Snakemake benchmark files of a surface's main steps."""
    steps = ["response", "calibrate", "poses", "observation", "holdout"]
    steps += [f"fit-{m}" for m in models()]
    return [f"logs/benchmarks/{sid}/{s}.tsv" for s in steps]


def surface_targets(sid):
    """Everything the workflow produces for one surface (the default target)."""
    R = f"{REPORTS}/{sid}"
    figs = [f"{R}/{f}.png" for f in ("contact_sheet", "response", "reexposure",
                                      "calibration", "radiometry", "view_directions",
                                      "pose_reprojection", "observation_valid_count",
                                      "observation_lobes")]
    figs += [f"{R}/{m}_{k}.png" for m in models() for k in ("params", "residuals", "lobes")]
    figs += [f"{R}/holdout.csv", f"{R}/holdout_regions.csv", f"{R}/holdout",
             f"{R}/sizes.csv", f"{R}/viewer", f"{R}/advice.png", f"{R}/lights.png"]
    if config["best"]["enabled"]:
        figs.append(f"{R}/best_choice.png")
    data = [f"{PROC}/{sid}/params/{m}.exr" for m in models() + ["diffuse"]]
    data += [f"{PROC}/{sid}/metrics/{m}.json" for m in ("hdr", "poses", "observation",
                                                        "holdout")]
    if config["fit"]["svbrdf"]["enabled"]:  # the relightable map for renderers
        data += [f"{PROC}/{sid}/params/svbrdf-ggx.gltf", f"{PROC}/{sid}/params/svbrdf-ggx.mtlx"]
    return figs + data


def fitted_view_ids(wildcards):
    """Ids of the views that are not held out."""
    checkpoints.validate_capture.get(sid=wildcards.sid)
    from parammap.stores.capture import load_capture

    return [v.id for v in load_capture(CAPTURES[wildcards.sid]).fitted_views]


def all_targets():
    return [t for sid in CAPTURES for t in surface_targets(sid)] + [
        f"{REPORTS}/summary.csv", f"{REPORTS}/summary.png"]


def synth_for(capdir):
    for sid, spec in SYNTH.items():
        if CAPTURES.get(sid) == capdir:
            return spec
    raise ValueError(f"no synth entry for {capdir}")


def synth_sid(capdir):
    return next(s for s in SYNTH if CAPTURES.get(s) == capdir)
