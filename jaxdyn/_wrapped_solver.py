"""A diffrax solver that wraps another and takes its properties."""

import diffrax
import equinox as eqx


class AbstractForwardingSolver(diffrax.AbstractWrappedSolver):
    """Wraps `solver`: its term structure, interpolation, orders and options are the wrapped
    solver's; subclasses define `init`, `step` and `func`."""

    solver: eqx.AbstractVar[diffrax.AbstractSolver]

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def __getattr__(self, name):
        # Options a diffrax adjoint reads or sets on Runge–Kutta solvers (ForwardMode,
        # `scan_kind`) are the wrapped solver's own.
        if name == "scan_kind":
            return getattr(self.solver, name)
        raise AttributeError(name)

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)
