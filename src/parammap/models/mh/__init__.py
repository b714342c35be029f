"""Multiple Highlight (MH) model: evaluation, initial guesses and the bounded fit.

``L_c(v) = Kd_c + sum_k Ks_kc * max(0, d_k . v) ** m`` per RGB channel, K lobes sharing
one shininess m (000 eq. 1, 004 eq. 11.2). Parameter vectors follow docs/reference/conventions.md
(:mod:`parammap.conventions`, ``mh_*``): ``Kd.R Kd.G Kd.B m`` then per lobe
``Ks.R Ks.G Ks.B d.X d.Y d.Z`` (4 + 6K values).

The optimiser works on ``x = [Kd(3), ln m, (Ks(3), theta, phi) per lobe]``
(``conventions.mhx_*``): polar angles keep each d a unit vector in the upper hemisphere
(theta in [0, pi/2]) and ln m keeps m in [1, 10000], so every constraint is a plain
bound, which all of nlopt's local gradient algorithms honour. Radiances are divided by
one per-texel scale before the fit (conditioning); Kd and Ks are multiplied back, so
stored parameters are in the observation map's radiance units.

Modules: :mod:`.model` (evaluation, metrics, x space), :mod:`.initial` (initial
guesses), :mod:`.fit` (batched LM, nlopt, lobe selection, a tile), :mod:`.repair`
(stains), :mod:`.kernel` (the compiled cost). Pure numerics: the map driver is
:func:`parammap.stages.fit.fit_mh_map`, the figures :func:`parammap.stages.figures.mh_figures`.
"""

from ..residuals import mean_percentage_residual
from .fit import K_MAX_AUTO, drop_negligible_lobes, fit_mh_tile, mh_outputs
from .initial import initial_guess_batch, initial_guess_published
from .model import M_MAX, M_MIN, bic, mh_eval, parse_lobes
from .optim import ALGORITHMS, FitResult, MhFitConfig, fit_texel, polish_batch, refine_batch
from .repair import REPAIR_FACTOR, REPAIR_RADIUS, REPAIR_STARTS, repair_mh_tile, stains

__all__ = [
    "ALGORITHMS",
    "K_MAX_AUTO",
    "M_MAX",
    "M_MIN",
    "REPAIR_FACTOR",
    "REPAIR_RADIUS",
    "REPAIR_STARTS",
    "FitResult",
    "MhFitConfig",
    "bic",
    "drop_negligible_lobes",
    "fit_mh_tile",
    "fit_texel",
    "initial_guess_batch",
    "initial_guess_published",
    "mean_percentage_residual",
    "mh_eval",
    "mh_outputs",
    "parse_lobes",
    "polish_batch",
    "refine_batch",
    "repair_mh_tile",
    "stains",
]
