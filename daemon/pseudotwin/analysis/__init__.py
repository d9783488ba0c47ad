"""Analysis: training, causal evaluation, plots and reports."""
