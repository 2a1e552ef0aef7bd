"""Signed multipliers pipelined in partial products that each fit one ECP5 MULT18X18D.

Yosys maps a wide product onto 18x18 blocks by itself, but then sums the partial products in one
combinational adder chain after them (no pipelining across it), and it puts even a 3-bit slice
of an operand on a block of its own. Here:

- each operand is cut into 17-bit unsigned slices and one signed top slice (a 17-bit unsigned
  slice is a non-negative 18-bit signed number, so every block multiplies signed 18x18);
- a top slice of at most ``LUT_BITS`` bits is multiplied in logic instead (shift-and-add), which
  saves a block per product for the 21-bit instruction-word values;
- the partial products are summed in a tree with a register after every level.

``latency`` is the number of clocks from ``a``/``b`` to ``p``; ``valid`` (if used) travels with
the operands.
"""

from migen import Module, Signal, Mux

SLICE = 17
LUT_BITS = 5


def slices(width):
    """(lsb, width, signed) of each slice of a signed operand of ``width`` bits."""
    out = []
    lsb = 0
    while width - lsb > SLICE + 1:
        out.append((lsb, SLICE, False))
        lsb += SLICE
    out.append((lsb, width - lsb, True))
    return out


class Multiplier(Module):
    """p = a * b, signed, in ``latency`` clocks (fully pipelined: one product per clock)."""

    def __init__(self, a_width, b_width):
        self.a = Signal((a_width, True))
        self.b = Signal((b_width, True))
        self.valid_in = Signal()
        self.p = Signal((a_width + b_width, True))
        self.valid = Signal()

        # Stage 0: the operands, registered.
        a = Signal((a_width, True))
        b = Signal((b_width, True))
        v = [Signal()]
        self.sync += [a.eq(self.a), b.eq(self.b), v[0].eq(self.valid_in)]

        # Stage 1: partial products (a's slices times b's slices, or a small top slice times b).
        terms = []
        for (alsb, awidth, asigned) in slices(a_width):
            part_a = Signal((awidth + (0 if asigned else 1), True))
            self.comb += part_a.eq(a[alsb:alsb + awidth])
            if asigned and awidth <= LUT_BITS and alsb > 0:
                terms.append((alsb, self._small_product(part_a, awidth, b, b_width)))
                continue
            for (blsb, bwidth, bsigned) in slices(b_width):
                part_b = Signal((bwidth + (0 if bsigned else 1), True))
                self.comb += part_b.eq(b[blsb:blsb + bwidth])
                pp = Signal((len(part_a) + len(part_b), True))
                self.sync += pp.eq(part_a * part_b)
                terms.append((alsb + blsb, pp))
        v.append(Signal())
        self.sync += v[-1].eq(v[-2])

        # Stages 2..: a tree of registered two-input sums, each term (shift, value).
        while len(terms) > 1:
            terms.sort(key=lambda t: t[0])
            level = []
            for i in range(0, len(terms) - 1, 2):
                (s0, x0), (s1, x1) = terms[i], terms[i + 1]
                width = max(len(x0) + s0, len(x1) + s1) - s0 + 1
                total = Signal((width, True))
                self.sync += total.eq(x0 + (x1 << (s1 - s0)))
                level.append((s0, total))
            if len(terms) % 2:
                s, x = terms[-1]
                held = Signal((len(x), True))
                self.sync += held.eq(x)
                level.append((s, held))
            terms = level
            v.append(Signal())
            self.sync += v[-1].eq(v[-2])
        shift, total = terms[0]
        self.comb += [self.p.eq(total << shift), self.valid.eq(v[-1])]
        self.latency = len(v)

    def _small_product(self, small, width, b, b_width):
        """small (signed, ``width`` bits) times b by shift-and-add in logic, registered."""
        out = Signal((b_width + width, True))
        terms = [Mux(small[k], -(b << k) if k == width - 1 else (b << k), 0)
                 for k in range(width)]
        total = terms[0]
        for t in terms[1:]:
            total = total + t
        self.sync += out.eq(total)
        return out
