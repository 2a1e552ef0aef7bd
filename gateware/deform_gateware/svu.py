"""The scalar–vector unit's vector passes (thesis 4.2.2, the VecALU and the Accumulator): one
element per clock, bit for bit ``target-core/src/svu.rs``'s portable passes
(``svu::portable_pass_r``, ``svu::portable_pass_xp``) for one direction.

α and β stay on the CPU: hart 0 plans each pass in integers (``svu::Lin::new``,
``svu::Narrow::new``) and writes the plan's fields into this unit's registers, exactly the
fields of the Rust plan structs:

- **Pass R** (``pass_xp`` = 0): r ← mulh_rounded(``r_mult``, narrow(Kp)) + own(r), then Σr²
  and the OR of the squares' high words. ``kp_right``/``kp_shift`` is ``svu::Narrow``
  (``Left(k)``: ``(kp as i32) << k``; ``Right(s)``: the funnel shift
  ``(lo >> s) | (hi << (32 − s))``); ``r_keep``/``r_left``/``r_right`` is ``PassR::lin.own``
  (``None``: the own term is 0; else ``(r << left) >> right``, arithmetic).
- **Pass XP** (``pass_xp`` = 1): with old = p[d] << ``p_shift`` (``Term::shift``, shared by
  both terms as the portable pass asserts), x ← mulh_rounded(``x_mult``, old) + own_x(x) if
  ``x_update``, p[d] ← own_r(r) + mulh(``p_mult``, old) if ``p_update``; the ORs of the new
  values' one's-complement magnitudes. An absent own shift is (0, 0), as
  ``lin.own.unwrap_or_default()`` in the portable pass (the identity, not 0 as in pass R).

Arithmetic, exactly as the Rust: every add wraps at 32 bits; mulh is bits 32..63 of the 64-bit
signed product, mulh_rounded the same of the product plus 2^31; squares are the 64-bit product
z·z; Σr² adds the squares in 64-bit blocks of 16 elements (wrapping, counted from the pass's
first element as ``chunks(16)`` counts them) and each block into a 96-bit total — exact for
every vector this unit holds (fewer than 2^32 blocks), as the firmware's assembly keeps it.
Shift amounts are 5-bit fields: Rust's ``wrapping_shl`` takes its amount modulo 32, and every
amount the planner makes (``Shift::by``, ``normalising_shift``, ``Narrow::new``) is below 32.
So the unit is exact for every vector and every plan the portable passes accept.

# Pipeline

One element enters per clock (``issue``); nothing stalls:

    I    read r[d][i], x[d][i] (this unit's memories), p[i] and Kp[i] (the ports below)
    +1   (block RAM, ``bram.LATENCY`` = 2)
    S    lane d of p and Kp; narrow Kp, old = p[d] << shift, the own terms' shifts
    M..  the two multipliers (``Multiplier.latency`` clocks)
    Z    z = high word (rounded or floored) + own term; written back in the next clock
    Q..  pass R: z·z (a third multiplier)
    A    Σr² blocks, the ORs; after the last element ``busy`` falls

A pass of n elements takes n + ``self.latency`` clocks.

# Memories, and how the unit will share the MVU array's p and Kp

r and x belong to the SVU alone: two block RAMs (``Bram``) inside the unit, 32 bits by
3·``nodes``, direction d's element i at ``d·nodes + i``. p and Kp live in the MVUs
(``mvu_array.py``: every MVU holds p twice, ``p_col`` and ``p_row``, and its own rows of Kp),
so the unit reaches them through ports of their shape, :class:`ReadPort` (read data
``bram.LATENCY`` clocks after the address) and :class:`WritePort`:

- ``p_read`` (entries of 96 bits, three lanes as ``kernel::Lanes`` without the padding) and
  ``p_write``: the whole entry is written back with lane d replaced. In the array, while the
  SVU runs (the MVUs idle), ``p_read`` is MVU 0's ``p_col.read[1]`` (the port the bus reads
  through; read port 0 shares the block's port A with the write) and ``p_write`` drives the
  write port of every MVU's ``p_col`` and ``p_row``, as a bus write of p does today.
- ``kp_read`` (entries of 192 bits, ``kernel::Sums``): the array presents the address to every
  MVU's ``kp`` and to its row-owner table (``owner``, the same latency once registered
  behind the block RAM) and returns the owner's entry (MVU 0's in plain mode), as the bus's
  Kp window does.

So no vector crosses the CPU: Kp from the MVU phase is read where the MVUs wrote it, and the
new p is where the next MVU phase reads it.
"""

from migen import Module, Signal, Array, Cat, If, Mux, Replicate
from litex.soc.interconnect.csr import AutoCSR, CSRStatus, CSRStorage

from deform_gateware.bram import Bram, LATENCY
from deform_gateware.multiplier import Multiplier
from deform_gateware.mvu import LANES, P_BITS, SUM_BITS, bits_for

WORD = 32
# Squares summed in a 64-bit block before they join the total (``svu::SQUARE_BLOCK``).
SQUARE_BLOCK = 16
# The total of Σr²: ⌈n/16⌉ blocks below 2^64 each.
RR_BITS = 96
# One one-bit-per-stage barrel shifter: 5 stages, amounts 0..31.
SHIFT_BITS = 5


class ReadPort:
    """A memory's read side: data ``bram.LATENCY`` clocks after the address."""

    def __init__(self, adr_bits, width):
        self.adr = Signal(adr_bits)
        self.dat = Signal(width)


class WritePort:
    def __init__(self, adr_bits, width):
        self.adr = Signal(adr_bits)
        self.dat_w = Signal(width)
        self.we = Signal()


def shift_left(v, amount):
    """``v.wrapping_shl(amount)`` on 32 bits (``amount``: a 5-bit signal)."""
    for k in range(SHIFT_BITS):
        step = 1 << k
        v = Mux(amount[k], Cat(Replicate(0, step), v[0:WORD - step]), v)
    return v


def shift_right(v, amount, arithmetic):
    """``v >> amount`` on 32 bits, arithmetic (i32) or logical (u32)."""
    sign = v[WORD - 1] if arithmetic else 0
    for k in range(SHIFT_BITS):
        step = 1 << k
        v = Mux(amount[k], Cat(v[step:WORD], Replicate(sign, step)), v)
    return v


def own_term(y, left, right):
    """``svu::Shift::apply``: ``y.wrapping_shl(left) >> right`` (arithmetic)."""
    return shift_right(shift_left(y, left), right, arithmetic=True)


def magnitude_bits(z):
    """``svu::magnitude_bits``: z ^ (z >> 31), |z| − 1 for negative z."""
    return z[0:WORD] ^ Replicate(z[WORD - 1], WORD)


class Svu(Module, AutoCSR):
    """Pass R and pass XP for one direction at a time, over vectors of up to ``nodes``
    elements (a power of two); ``primitive``: ECP5 block RAM primitives for r and x."""

    def __init__(self, nodes=1024, primitive=False):
        assert nodes >= SQUARE_BLOCK and nodes & (nodes - 1) == 0, "nodes: a power of two ≥ 16"
        self.nodes_depth = nodes
        nb = bits_for(nodes)
        self._csrs()

        self.p_read = ReadPort(nb, LANES * P_BITS)
        self.p_write = WritePort(nb, LANES * P_BITS)
        self.kp_read = ReadPort(nb, LANES * SUM_BITS)
        self.submodules.r = Bram(WORD, LANES * nodes, primitive=primitive)
        self.submodules.x = Bram(WORD, LANES * nodes, primitive=primitive)

        control, running = self._issue(nb)
        s_control, s_entry, operand, own_a, own_b = self._operands(control)
        z_a, z_control = self._update(s_control, s_entry, operand, own_a, own_b)
        self.latency = LATENCY + 1 + self._mul_latency + 1 + self._sum_squares(
            z_a, z_control, running)

    def _csrs(self):
        self.n = CSRStorage(32, description="Elements in the pass (0 .. nodes)")
        self.direction = CSRStorage(2, description="The direction (lane of p and Kp), 0 to 2")
        self.pass_xp = CSRStorage(1, description="0: pass R (r, Σr²); 1: pass XP (x, p)")
        self.start = CSRStorage(1, description="Write to run the pass")
        self.busy = CSRStatus(1, description="A pass is running")
        # Pass R: PassR { lin, narrow }.
        self.r_mult = CSRStorage(32, description="Pass R: lin.term.mult, A of the α·Kp term")
        self.kp_right = CSRStorage(1, description="Pass R: narrow is Narrow::Right")
        self.kp_shift = CSRStorage(SHIFT_BITS, description="Pass R: narrow's k or s")
        self.r_keep = CSRStorage(1, description="Pass R: lin.own is Some (r keeps its term)")
        self.r_left = CSRStorage(SHIFT_BITS, description="Pass R: lin.own's left shift")
        self.r_right = CSRStorage(SHIFT_BITS, description="Pass R: lin.own's right shift")
        # Pass XP: PassXP { x, p }.
        self.p_shift = CSRStorage(SHIFT_BITS, description="Pass XP: term.shift of old p")
        self.x_update = CSRStorage(1, description="Pass XP: x is updated (plan.x is Some)")
        self.x_mult = CSRStorage(32, description="Pass XP: x.term.mult, A of α·p")
        self.x_left = CSRStorage(SHIFT_BITS, description="Pass XP: x.own's left shift")
        self.x_right = CSRStorage(SHIFT_BITS, description="Pass XP: x.own's right shift")
        self.p_update = CSRStorage(1, description="Pass XP: p is updated (plan.p is Some)")
        self.p_mult = CSRStorage(32, description="Pass XP: p.term.mult, A of β·p")
        self.r_into_p_left = CSRStorage(SHIFT_BITS, description="Pass XP: p.own's left shift")
        self.r_into_p_right = CSRStorage(SHIFT_BITS,
                                         description="Pass XP: p.own's right shift")
        # Results.
        self.rr = CSRStatus(RR_BITS, description="Pass R: Σr², exact")
        self.r_or = CSRStatus(WORD, description="Pass R: OR of the high words of r²")
        self.x_or = CSRStatus(WORD, description="Pass XP: OR of |x| (one's complement)")
        self.p_or = CSRStatus(WORD, description="Pass XP: OR of |p| (one's complement)")

    def _issue(self, nb):
        """I: one element per clock from ``start``; returns what travels with each element
        (valid, last, index), ``bram.LATENCY`` clocks later, and the ``running`` flag."""
        d = self.direction.storage
        issuing = Signal()
        index = Signal(nb + 1)
        count = self.n.storage
        last = Signal()
        # n beyond the memories ends at their last element.
        self.comb += last.eq((index == count - 1) | (index == self.nodes_depth - 1))
        adr_mem = Signal(nb + 2)
        self.comb += [
            adr_mem.eq(Cat(index[0:nb], d)),
            self.r.read[0].adr.eq(adr_mem), self.x.read[0].adr.eq(adr_mem),
            self.p_read.adr.eq(index), self.kp_read.adr.eq(index),
        ]
        self.done = done = Signal()
        running = Signal()
        self.comb += self.busy.status.eq(running)
        self.sync += [
            If(self.start.re & ~running & (count != 0),
                issuing.eq(1), running.eq(1), index.eq(0),
                self.rr.status.eq(0), self.r_or.status.eq(0),
                self.x_or.status.eq(0), self.p_or.status.eq(0),
            ).Elif(self.start.re & ~running,
                self.rr.status.eq(0), self.r_or.status.eq(0),
                self.x_or.status.eq(0), self.p_or.status.eq(0),
            ).Elif(issuing,
                index.eq(index + 1),
                If(last, issuing.eq(0))),
            If(done, running.eq(0)),
        ]
        # What travels with an element: valid, last, its index.
        control = Cat(issuing, last, index[0:nb])
        return self._delay(control, LATENCY), running

    def _operands(self, at_s):
        """S: the lanes of p and Kp, the narrowing, the shifts, registered: the multipliers'
        operand and the own terms."""
        d = self.direction.storage
        xp = self.pass_xp.storage
        p_entry = self.p_read.dat
        kp = Signal((SUM_BITS, True))
        p_lane = Signal(WORD)
        self.comb += [
            kp.eq(Array([self.kp_read.dat[SUM_BITS * k:SUM_BITS * (k + 1)]
                         for k in range(LANES)])[d]),
            p_lane.eq(Array([p_entry[WORD * k:WORD * (k + 1)] for k in range(LANES)])[d]),
        ]
        amount = self.kp_shift.storage
        funnel = Signal(SHIFT_BITS)         # (32 − s) mod 32, Rust's wrapping_shl(32 − s)
        self.comb += funnel.eq(-amount)
        narrowed = Mux(self.kp_right.storage,
                       shift_right(kp[0:WORD], amount, arithmetic=False)
                       | shift_left(kp[WORD:SUM_BITS], funnel),
                       shift_left(kp[0:WORD], amount))
        old = shift_left(p_lane, self.p_shift.storage)
        r_in = self.r.read[0].dat
        x_in = self.x.read[0].dat
        operand = Signal((WORD, True))      # narrowed Kp (R) or old p (XP)
        own_a = Signal(WORD)                # own r (R) or own x (XP)
        own_b = Signal(WORD)                # own r into p (XP)
        s_control = Signal(len(at_s))
        s_entry = Signal(LANES * P_BITS)
        self.sync += [
            operand.eq(Mux(xp, old, narrowed)),
            own_a.eq(Mux(xp, own_term(x_in, self.x_left.storage, self.x_right.storage),
                         Mux(self.r_keep.storage,
                             own_term(r_in, self.r_left.storage, self.r_right.storage), 0))),
            own_b.eq(own_term(r_in, self.r_into_p_left.storage, self.r_into_p_right.storage)),
            s_control.eq(at_s), s_entry.eq(p_entry),
        ]
        return s_control, s_entry, operand, own_a, own_b

    def _update(self, s_control, s_entry, operand, own_a, own_b):
        """M, Z: the products, z = high word + own term (registered), the write-backs and the
        ORs of pass XP; returns z_a (new r or x) and what travels with it."""
        d = self.direction.storage
        xp = self.pass_xp.storage
        # M: the rounded term (α·Kp or α·p) and the floored one (β·p).
        rounded_mul = Multiplier(WORD, WORD)
        floored_mul = Multiplier(WORD, WORD)
        self.submodules += rounded_mul, floored_mul
        self._mul_latency = mul_latency = rounded_mul.latency
        self.comb += [
            rounded_mul.a.eq(Mux(xp, self.x_mult.storage, self.r_mult.storage)),
            rounded_mul.b.eq(operand),
            floored_mul.a.eq(self.p_mult.storage), floored_mul.b.eq(operand),
        ]
        m_control = self._delay(s_control, mul_latency)
        m_own_a = self._delay(own_a, mul_latency)
        m_own_b = self._delay(own_b, mul_latency)
        m_entry = self._delay(s_entry, mul_latency)

        # Z: z = high word + own term, wrapping at 32 bits; registered, then written.
        rounded = Signal(2 * WORD + 1)
        self.comb += rounded.eq(rounded_mul.p + (1 << (WORD - 1)))
        z_a = Signal((WORD, True))          # new r (R) or new x (XP)
        z_b = Signal((WORD, True))          # new p[d] (XP)
        z_control = Signal(len(s_control))
        z_entry = Signal(LANES * P_BITS)
        self.sync += [
            z_a.eq(rounded[WORD:2 * WORD] + m_own_a),
            z_b.eq(m_own_b + floored_mul.p[WORD:2 * WORD]),
            z_control.eq(m_control), z_entry.eq(m_entry),
        ]
        z_valid, z_index = z_control[0], z_control[2:]  # bit 1 (last) has no use here
        new_entry = Signal(LANES * P_BITS)
        self.comb += new_entry.eq(z_entry)
        self.comb += Array([new_entry[WORD * k:WORD * (k + 1)] for k in range(LANES)])[d].eq(z_b)
        z_adr = Cat(z_index, d)
        self.comb += [
            self.r.adr.eq(z_adr), self.r.dat_w.eq(z_a), self.r.we.eq(z_valid & ~xp),
            self.x.adr.eq(z_adr), self.x.dat_w.eq(z_a),
            self.x.we.eq(z_valid & xp & self.x_update.storage),
            self.p_write.adr.eq(z_index), self.p_write.dat_w.eq(new_entry),
            self.p_write.we.eq(z_valid & xp & self.p_update.storage),
        ]
        self.sync += If(z_valid & xp,
            If(self.x_update.storage, self.x_or.status.eq(self.x_or.status | magnitude_bits(z_a))),
            If(self.p_update.storage, self.p_or.status.eq(self.p_or.status | magnitude_bits(z_b))))
        return z_a, z_control

    def _sum_squares(self, z_a, z_control, running):
        """Q, A: pass R's square, its block of 16 and the total; the end of the pass.
        Returns the square's latency."""
        xp = self.pass_xp.storage
        square_mul = Multiplier(WORD, WORD)
        self.submodules += square_mul
        self.comb += [square_mul.a.eq(z_a), square_mul.b.eq(z_a)]
        q_control = self._delay(z_control, square_mul.latency)
        q_valid, q_last, q_index = q_control[0], q_control[1], q_control[2:]
        square = square_mul.p[0:2 * WORD]
        block = Signal(2 * WORD)
        block_sum = Signal(2 * WORD)
        self.comb += block_sum.eq(block + square)
        block_end = (q_index[0:4] == SQUARE_BLOCK - 1) | q_last
        self.sync += [
            If(self.start.re & ~running, block.eq(0)),
            If(q_valid & ~xp,
                self.r_or.status.eq(self.r_or.status | square[WORD:2 * WORD]),
                If(block_end,
                    self.rr.status.eq(self.rr.status + block_sum), block.eq(0),
                ).Else(block.eq(block_sum))),
        ]
        self.comb += self.done.eq(q_valid & q_last)
        return square_mul.latency

    def _delay(self, signal, clocks):
        """``signal`` ``clocks`` clocks later, through a chain of registers."""
        for _ in range(clocks):
            held = Signal(len(signal))
            self.sync += held.eq(signal)
            signal = held
        return signal
