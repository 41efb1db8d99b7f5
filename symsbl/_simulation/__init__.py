"""Systems and simulation: :class:`~symsbl.OdeSystem`, forcing signals, the compiled RK4 stepper, CVODES and
the :func:`~symsbl.simulate` entry point."""
