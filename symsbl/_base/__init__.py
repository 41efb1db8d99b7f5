"""Plumbing every stage shares: the package's errors, argument checks, CasADi compilation with its fallback
and cache, interrupts, progress lines, number formatting, safe output files and the selection rule."""
