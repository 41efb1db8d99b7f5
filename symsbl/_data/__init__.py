"""Records: :class:`~symsbl.Trajectory` (sampled states and inputs, noise levels), reading and writing data
files, and the statistics of residuals (whiteness, effective sample size)."""
