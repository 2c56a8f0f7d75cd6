"""The learner's analysis tools: sweep reports, plots, comparisons, videos, self-checks and the Gymnasium view."""
