"""Precomputed slope tables: what the calculator reads instead of simulating.

For every SCA (1-18) and imaging band, on a magnitude grid from 1.5 mag brighter than saturation
to m = 28 in steps of 0.25 mag (0.125 mag up to a magnitude fainter than saturation), the table
holds at the paper's defaults (168.1 s, beta0 = 5e-7, N = 3, 96 x 96, 100 centroid realizations,
seed 1, weight cut rho^2 = 25):

- bias slopes d(Delta R/R)/d beta, d(Delta e1)/d beta, d(Delta e2)/d beta at beta0 (paper Fig. 3),
- scatter slopes sigma(metric)/sigma_beta for independent per-pixel beta (paper Fig. 5),

each with the standard error of its mean over the centroid realizations. They are computed with
the linear response at beta0 (exact derivatives of the converged moments at the NL-distorted
image, ``experiment.slopes(method="linear")``), which the tests check against the paper's Monte
Carlo finite differences.

Reading the tables at other conditions is exact, not an approximation: the metrics depend on beta
and flux only through beta * flux, so for exposure t and beta0

    slope(m; t, beta0) = (beta0_table / beta0) * slope_table(m - 2.5 log10(beta0 t / (beta0_table t_table)))

and the same for the scatter slopes; the full well only moves the saturation magnitude. Between
grid points slope / flux is interpolated with a cubic spline (it is smooth and nearly constant at
the faint end); the interpolation error, estimated by leaving each grid point out in turn
(``tablebuild.interpolation_error_estimate``), is stored with the table and added to the stated
uncertainty. Fainter than the grid the slopes follow the linear regime exactly (slope
proportional to flux); brighter than the grid there is no answer.

The shipped tables are one runtime file, ``slopes.npz`` (``nlpsf tables export`` writes them as
ECSV). A second file (``field_slopes.npz``, ``nlpsf tables build --field``) holds the same tables at
each SCA's four corner field points, keyed (band, SCA, field point): ``TableSet.at_point`` gives the
tables at one corner keyed like the centre's, which is how ``solver.solve`` reads them for a star at
a corner (``solve_over_field`` asks for every corner).

The package, by what each module holds (everything is importable from ``nlpsf.slopes.tables``):

- ``model``: ``SlopeTable`` (one table, its lookups and rescaling), ``TableSet``, relabelling to
  another throughput (``with_throughput``), the column names;
- ``splines``: the cubic splines in scipy's public ``PPoly`` layout (built with ``CubicSpline`` where
  a table is written), evaluated with numpy;
- ``storage``: where the shipped files are, the runtime file (written and read: rows and spline
  coefficients), the ECSV read by astropy when there is no matching runtime file, the ECSV export;
- ``curves``: slope curves and flat rows for plotting and download, with their conditions;
- ``paper``: the paper's power-law fits (Table 2) and its published figure data.

Building tables (simulations) is ``nlpsf.slopes.tablebuild``.
"""

from __future__ import annotations

from .curves import check_metric_mode, conditions, curve, table_rows
from .model import (
    BRIGHT_MARGIN_MAG,
    COLUMN_METRICS,
    METRICS,
    MODES,
    RELABEL_ERROR,
    SLOPE_COLUMNS,
    SlopeTable,
    TableSet,
    table_key,
    with_throughput,
)
from .paper import PAPER_FIT_RANGE, paper_data, powerlaw_fit, powerlaw_fits, table2_comparison, table2_markdown
from .splines import evaluate_cubic, not_a_knot_spline
from .storage import (
    COMPANION_FORMAT,
    KEY_COLUMNS,
    META_KEYS,
    companion_path,
    ecsv_fingerprint,
    export_ecsv,
    field_table_path,
    groups,
    load_ecsv,
    load_tables,
    shipped_table_path,
    write_companion,
    write_ecsv,
)

__all__ = [
    "BRIGHT_MARGIN_MAG",
    "COLUMN_METRICS",
    "COMPANION_FORMAT",
    "KEY_COLUMNS",
    "META_KEYS",
    "METRICS",
    "MODES",
    "PAPER_FIT_RANGE",
    "RELABEL_ERROR",
    "SLOPE_COLUMNS",
    "SlopeTable",
    "TableSet",
    "check_metric_mode",
    "companion_path",
    "conditions",
    "curve",
    "ecsv_fingerprint",
    "evaluate_cubic",
    "export_ecsv",
    "field_table_path",
    "groups",
    "load_ecsv",
    "load_tables",
    "not_a_knot_spline",
    "paper_data",
    "powerlaw_fit",
    "powerlaw_fits",
    "shipped_table_path",
    "table2_comparison",
    "table2_markdown",
    "table_key",
    "table_rows",
    "with_throughput",
    "write_companion",
    "write_ecsv",
]
