"""Signed multipliers pipelined in partial products that each fit one ECP5 MULT18X18D.

Yosys maps a wide product onto 18x18 blocks by itself, but then sums the partial products in one
combinational adder chain after them (no pipelining across it), and it puts even a 3-bit slice
of an operand on a block of its own. Here:

- each operand is cut into 17-bit unsigned slices and one signed top slice (a 17-bit unsigned
  slice is a non-negative 18-bit signed number, so every block multiplies signed 18x18);
- a top slice of at most ``LUT_BITS`` bits is multiplied in logic instead (shift-and-add, two
  bits per registered term, so that no clock holds more than one adder), which saves a block per
  product for the 21-bit instruction-word values;
- the partial products are summed in a tree with a register after every level;
- ``primitive=True`` (ECP5): each 18x18 product is a MULT18X18D instantiated with its input and
  output registers on, in place of the operand and product registers of the generic path (same
  latency). Yosys never uses those registers itself, and an inferred block then sits between
  fabric registers with routing on both sides: 115 MHz measured for one MVU, where the block's
  own registers leave it the multiply alone. Simulation (Migen, Verilator) uses the generic path.

``latency`` is the number of clocks from ``a``/``b`` to ``p``; ``valid`` (if used) travels with
the operands.
"""

from migen import Module, Signal, Mux, Cat, Replicate, Instance, ClockSignal

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

    def __init__(self, a_width, b_width, primitive=False):
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
                terms += self._small_product(part_a, alsb, awidth, b, b_width)
                continue
            for (blsb, bwidth, bsigned) in slices(b_width):
                pp = Signal((awidth + bwidth + (0 if asigned else 1) + (0 if bsigned else 1),
                             True))
                if primitive:
                    # Sliced from the unregistered operands: the block's input registers
                    # are stage 0, its output register stage 1.
                    self._block(self.a[alsb:alsb + awidth], asigned,
                                self.b[blsb:blsb + bwidth], bsigned, pp)
                else:
                    part_b = Signal((bwidth + (0 if bsigned else 1), True))
                    self.comb += part_b.eq(b[blsb:blsb + bwidth])
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

    def _block(self, a_part, a_signed, b_part, b_signed, pp):
        """pp = a_part * b_part on a MULT18X18D with its input and output registers on (two
        clocks, as the operand and product registers of the generic path): the block's own
        multiplier alone between two registers, ~4 ns at speed grade 6 that an inferred
        block puts between fabric registers, with routing on both sides (115 MHz measured).
        Both operands go in as signed 18-bit numbers (a 17-bit slice zero-extended)."""
        def extended(part, signed):
            top = part[-1] if signed else 0
            return Cat(part, Replicate(top, 18 - len(part)))
        ia, ib, op = Signal(18), Signal(18), Signal(36)
        self.comb += [ia.eq(extended(a_part, a_signed)), ib.eq(extended(b_part, b_signed)),
                      pp.eq(op[0:len(pp)])]
        ports = dict(
            p_REG_INPUTA_CLK="CLK0", p_REG_INPUTB_CLK="CLK0", p_REG_OUTPUT_CLK="CLK0",
            p_REG_INPUTC_CLK="NONE", p_REG_PIPELINE_CLK="NONE", p_GSR="DISABLED",
            p_RESETMODE="SYNC", p_MULT_BYPASS="DISABLED",
            i_CLK0=ClockSignal(), i_CE0=1, i_RST0=0, i_SIGNEDA=1, i_SIGNEDB=1,
            i_SOURCEA=0, i_SOURCEB=0,
        )
        for k in range(1, 4):
            ports["i_CLK%d" % k] = 0
            ports["i_CE%d" % k] = 0
            ports["i_RST%d" % k] = 0
        for k in range(18):
            ports["i_A%d" % k] = ia[k]
            ports["i_B%d" % k] = ib[k]
            ports["i_C%d" % k] = 0
        for k in range(36):
            ports["o_P%d" % k] = op[k]
        self.specials += Instance("MULT18X18D", **ports)

    def _small_product(self, small, shift, width, b, b_width):
        """small (signed, ``width`` bits, at bit ``shift`` of a) times b by shift-and-add in
        logic: the terms (shift, value), each the registered sum of two of small's bits times
        b (one adder in the clock, as long as a block's product takes; the tree adds them).
        The sign bit's term is subtracted, not added negated: a negation is a carry chain of
        its own, in series with the adder's."""
        def magnitude(k):
            return Mux(small[k], b << k, 0)
        terms = []
        for k in range(0, width, 2):
            out = Signal((b_width + min(width, k + 2) + 1, True))
            if k + 1 < width:
                if k + 1 == width - 1:
                    self.sync += out.eq(magnitude(k) - magnitude(k + 1))
                else:
                    self.sync += out.eq(magnitude(k) + magnitude(k + 1))
            elif k == width - 1:
                self.sync += out.eq(0 - magnitude(k))
            else:
                self.sync += out.eq(magnitude(k))
            terms.append((shift, out))
        return terms
