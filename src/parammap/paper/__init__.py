"""Regenerate the published experiments of 004 (and 000) under the published conditions.

``parammap paper --out reports/paper`` (``make paper``) writes one CSV per experiment
with the published figure, ours under the published method and ours under our
defaults, and ``reports/paper/README.md`` with the conditions chosen where the thesis
leaves them unstated. Experiments (004 chapter in brackets):

- ``point_area`` (11.3.1): one point light, then a small area light; MH, one lobe.
- ``second_light`` (11.3.2): a second, weaker light ever further away; one lobe as
  published, then two lobes and ``auto``.
- ``sh_sweep`` (12.5): SH with 16 ... 100 coefficients, ZH and LSOP as published (and
  mirror), against our sampled-cap projections; residuals and the values near the
  equator.
- ``shininess`` (13.1): eight bands of increasing shininess; the highest each model
  follows.
- ``view_count`` (13.2-13.3): 17 / 73 / 305 views and the non-uniform 73 + 81.
- ``initialisers`` (001): the greedy virtual lights against 004's initial guess.
- ``holdout`` (16, tables 16.1 / 16.2): held-out views of one of our captures, with
  the models 004 compared (given a capture and its processed folder).
- ``sizes`` (tables 9.1, 11.1, 12.1): storage by formula, as published, and measured
  for our EXR files.
- ``sampling`` (8.1): the spiral and latitude-longitude schemes as published, with a
  coverage figure each.

The published conditions (004 ch. 11.3): a 1000 x 1000 surface in 16 x 16 texels, a
white point light at [1500, 1500, 2000] from the surface centre, a Phong material of
colour [200, 15, 15], 289 icosahedron views, renders in 8 bits (clipped at 255).
"""

from __future__ import annotations

import inspect
import logging
from pathlib import Path

from ..config import default
from ..errors import InputError
from ..synth.sampling import icosahedron
from .analytic import (
    exp_initialisers,
    exp_point_area,
    exp_sampling,
    exp_second_light,
    exp_sh_sweep,
    exp_shininess,
    exp_sizes,
    exp_view_count,
)
from .capture import exp_holdout, measured_sizes
from .common import CONDITIONS, _write_csv

__all__ = ["CONDITIONS", "EXPERIMENTS", "run_paper"]

logger = logging.getLogger(__name__)


EXPERIMENTS = {"point_area": exp_point_area, "second_light": exp_second_light,
               "sh_sweep": exp_sh_sweep, "shininess": exp_shininess,
               "view_count": exp_view_count, "initialisers": exp_initialisers,
               "sizes": exp_sizes, "sampling": exp_sampling}


def run_paper(out_dir: str | Path, experiments: list[str] | None = None,
              quick: bool = False, capture: str | Path | None = None,
              processed: str | Path | None = None, workers: int = default("workers")) -> list[Path]:
    """Run the experiments (default: all) and write ``<out_dir>/<experiment>.csv`` and
    ``<out_dir>/README.md`` (conditions and the values chosen where 004 is silent).
    ``quick`` runs a reduced SH sweep (16 and 100 coefficients) for the test suite.
    With a ``capture`` and its ``processed`` folder, 004 ch. 16's held-out tables are
    added (``holdout.csv``, :func:`exp_holdout`)."""
    out = Path(out_dir)
    names = experiments or list(EXPERIMENTS)
    paths = []
    for name in names:
        if name not in EXPERIMENTS:

            raise InputError(f"unknown experiment {name!r} (one of {', '.join(EXPERIMENTS)})")
        logger.info(f"paper: {name}")
        fn = EXPERIMENTS[name]
        kw = {"bands": (4, 10)} if name == "sh_sweep" and quick else {}
        if "out_dir" in inspect.signature(fn).parameters:
            kw["out_dir"] = out
        rows = fn(**kw)
        paths += [p for p in (out / f"{name}.png",) if p.is_file()]
        paths.append(_write_csv(out / f"{name}.csv", rows))
    if capture is not None and processed is not None:
        logger.info("paper: holdout (004 ch. 16)")
        paths.append(_write_csv(out / "holdout.csv", exp_holdout(capture, processed,
                                                                 workers, quick)))
        paths.append(_write_csv(out / "sizes_measured.csv", measured_sizes(processed)))
    lines = ["# 004 / 000 experiments under the published conditions", "",
             "Conditions 004 leaves unstated, and the values chosen:", ""]
    lines += [f"- {k}: {v}" for k, v in CONDITIONS.why.items()]
    n_views = len(icosahedron(CONDITIONS.views_level, CONDITIONS.views_max_zenith_deg))
    lines += ["", f"Views: {n_views} icosahedron directions; observations quantised to 8 "
              "bits, clipped at 255.",
              "Columns: published figure, ours with the published method (004's initial "
              "guess; ZH / mirror / LSOP as 004 defines them), ours with our defaults."]
    readme = out / "README.md"
    readme.write_text("\n".join(lines) + "\n")
    return paths + [readme]
