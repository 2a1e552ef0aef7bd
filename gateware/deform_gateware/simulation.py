"""Migen's simulator for the gateware's tests, with value widths computed once.

Why a patch of our own: Migen computes a value's width anew on every ``len()``
(``bitcontainer.value_bits_sign``, recursively through ``Cat``\\ s and operators), and its
simulator asks for widths at every evaluation and assignment of a ``Cat``. In the block-RAM
wiring test at 1,024 rows that was more than half of the run (cProfile: 64 of 116 s in
``len``). No release of Migen caches it, and Amaranth's simulator would mean a second HDL.
A value's width does not change once it is built: a ``Signal``'s or ``Constant``'s is its
``nbits``, and any other value's is kept on it at its first ``len()``.

Only the tests import this module, so the Verilog that LiteX builds never runs through it.
"""

from migen import run_simulation as _run_simulation
from migen.fhdl import structure
from migen.fhdl.bitcontainer import value_bits_sign


def _nbits(value):
    return value.nbits


def _kept_width(value):
    width = value.__dict__.get("_deform_width")
    if width is None:
        width = value_bits_sign(value)[0]
        value.__dict__["_deform_width"] = width
    return width


def install():
    """Widths once per value, for every simulation from here on (idempotent)."""
    structure.Signal.__len__ = _nbits
    structure.Constant.__len__ = _nbits
    structure._Value.__len__ = _kept_width


def run_simulation(*args, **kwargs):
    """Migen's ``run_simulation``, with :func:`install` done first."""
    install()
    return _run_simulation(*args, **kwargs)
