"""Results that last: saved designs (bit-exact), results folders, Markdown reports, figures.
Every file is written atomically, inside the folder chosen for it."""

from ._io import (
    atomic_write_bytes as atomic_write_bytes,
    atomic_write_json as atomic_write_json,
    atomic_write_npz as atomic_write_npz,
    atomic_write_text as atomic_write_text,
    load_design as load_design,
    new_results_folder as new_results_folder,
    read_design_metadata as read_design_metadata,
    save_design as save_design,
    write_metrics as write_metrics,
)
from ._plots import (
    plot_error_distributions as plot_error_distributions,
    plot_estimates as plot_estimates,
    plot_poles as plot_poles,
    plot_tuning_curve as plot_tuning_curve,
)
from ._report import markdown_table as markdown_table, write_report as write_report
