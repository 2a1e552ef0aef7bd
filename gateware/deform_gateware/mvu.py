"""One matrix-vector unit (thesis 4.2.1, Fig. 4-6): Kp = K·p for up to three fused directions,
one instruction word per clock, with its row write-backs, pᵀKp and max |Kp|.

What it computes is ``target-core``'s portable kernel (``kernel::portable_row``,
``kernel::p_kp_and_max``) bit for bit; how its memories are filled is
``target-core/src/mvu_program.rs``.

Memories (all loaded between phases by the MVU array's bus; the unit only reads them, except Kp):

- ``words``: 36-bit entries, the instruction words of its tiles back to back and the write-back
  flags of each ER word (``word.FIRST_OWN`` ...);
- ``tiles``: per tile ``row_base``, ``col_base`` and the mirrored bit; EM moves to the next one;
- ``p_col``: p (three 32-bit lanes per node), read twice per clock: at column ``col_base + c``
  and, for a mirrored tile, at ``n - 1 - col_base - c``;
- ``p_row``: another copy of p, read at the row of each write-back (for pᵀKp);
- ``kp``: this unit's Kp, three 64-bit sums per row.

The word pipeline (no stage ever stalls; the fetch waits instead):

    F0 fetch   the word memory at ``wa``
    F1 decode  EM/ER/column/value/flags; the p addresses from the tile context
    F2         p read; the multipliers take value x p for 3 lanes, own and mirrored
    M ...      the multipliers' pipeline (``Multiplier.latency`` clocks)
    A          accumulate, 64 bits per lane; an ER word's sums are complete after it
    E          an ER word's sums (and rows, flags) go into the write-back queue

The write-back takes queue entries one part at a time (the own row, then the mirror row of a
mirrored tile), two clocks each: read Kp and p at the row, then store (first write-back of the
row in this phase) or add, OR the magnitudes into max |Kp| if this was the row's last
write-back, and hand p[row] and the sums to the pᵀKp sequencer, which multiplies each lane's
32-bit p by the sum's low and high halves in turn (2 clocks per direction) and accumulates
Σ p·low and Σ p·high; the array joins them into pᵀKp. The fetch stops while the queue could
overflow; ``stalls`` counts those clocks.
"""

from migen import (Module, Signal, Memory, Array, Cat, If, Case, FSM, NextState, NextValue,
                   Replicate)
from migen.genlib.fifo import SyncFIFO

from deform_gateware.multiplier import Multiplier
from deform_gateware.word import (InstructionWord, ENTRY_BITS, VALUE_BITS, FIRST_OWN, LAST_OWN,
                                  FIRST_MIRROR, LAST_MIRROR)

LANES = 3
P_BITS = 32
SUM_BITS = 64
# Σ p·(half of a row sum) over at most 2^17 write-backs of |p| < 2^31, |half| < 2^32: 81 bits.
HALF_SUM_BITS = 84
QUEUE_DEPTH = 16


def bits_for(n):
    """Bits to hold 0 .. n - 1 (at least one)."""
    return max(1, (n - 1).bit_length())


def lanes(signal, width, count=LANES):
    """The ``count`` signed ``width``-bit lanes of ``signal``, as signed signals (and the
    statements that fill them)."""
    out = [Signal((width, True)) for _ in range(count)]
    return out, [o.eq(signal[width * i:width * (i + 1)]) for i, o in enumerate(out)]


def magnitude(v):
    """``v ^ (v >> 63)``: the one's-complement magnitude the kernel ORs into max |Kp|."""
    return v[0:SUM_BITS] ^ Replicate(v[SUM_BITS - 1], SUM_BITS)


class BusPort:
    """The side of a memory port the MVU array drives while the unit is idle."""

    def __init__(self, adr_bits, width, write=False):
        self.adr = Signal(adr_bits)
        self.dat_r = Signal(width)
        self.dat_w = Signal(width) if write else None
        self.we = Signal() if write else None


class Mvu(Module):
    """One MVU: ``words`` word entries, ``tiles`` tiles, p and Kp for ``nodes`` rows."""

    def __init__(self, words, tiles, nodes):
        self.words_depth, self.tiles_depth, self.nodes_depth = words, tiles, nodes
        nb = bits_for(nodes)
        self.node_bits = nb

        # Set by the array.
        self.start = Signal()
        self.last_row = Signal(nb)              # n - 1
        self.directions = Signal(2)             # 1..3
        self.length = Signal(bits_for(words + 1))  # words to run (0: sit the phase out)
        # Status and results.
        self.busy = Signal()
        self.stalls = Signal(32)
        self.p_kp_low = [Signal((HALF_SUM_BITS, True)) for _ in range(LANES)]
        self.p_kp_high = [Signal((HALF_SUM_BITS, True)) for _ in range(LANES)]
        self.kp_or = [Signal(SUM_BITS) for _ in range(LANES)]

        # Memories, and the ports the array uses while the unit is idle.
        self.specials.word_mem = word_mem = Memory(ENTRY_BITS, words)
        self.specials.tile_mem = tile_mem = Memory(2 * nb + 1, tiles)
        self.specials.p_col = p_col = Memory(LANES * P_BITS, nodes)
        self.specials.p_row = p_row = Memory(LANES * P_BITS, nodes)
        self.specials.kp_mem = kp_mem = Memory(LANES * SUM_BITS, nodes)
        self.bus_word = BusPort(bits_for(words), ENTRY_BITS, write=True)
        self.bus_tile = BusPort(bits_for(tiles), 2 * nb + 1, write=True)
        self.bus_p = BusPort(nb, LANES * P_BITS, write=True)   # writes both copies, reads p_col
        self.bus_kp = BusPort(nb, LANES * SUM_BITS, write=True)

        word_rd = word_mem.get_port()
        word_wr = word_mem.get_port(write_capable=True)
        tile_rd = tile_mem.get_port()
        tile_wr = tile_mem.get_port(write_capable=True)
        p_own = p_col.get_port(write_capable=True)
        p_mirror = p_col.get_port()
        p_at_row = p_row.get_port()
        p_row_wr = p_row.get_port(write_capable=True)
        kp_rd = kp_mem.get_port()
        kp_wr = kp_mem.get_port(write_capable=True)
        self.specials += [word_rd, word_wr, tile_rd, tile_wr, p_own, p_mirror, p_at_row,
                          p_row_wr, kp_rd, kp_wr]

        # The array's ports: writes only while idle; reads share the unit's read ports.
        idle = ~self.busy
        self.comb += [
            word_wr.adr.eq(self.bus_word.adr), word_wr.dat_w.eq(self.bus_word.dat_w),
            word_wr.we.eq(self.bus_word.we & idle), self.bus_word.dat_r.eq(word_rd.dat_r),
            tile_wr.adr.eq(self.bus_tile.adr), tile_wr.dat_w.eq(self.bus_tile.dat_w),
            tile_wr.we.eq(self.bus_tile.we & idle), self.bus_tile.dat_r.eq(tile_rd.dat_r),
            p_own.dat_w.eq(self.bus_p.dat_w), p_own.we.eq(self.bus_p.we & idle),
            p_row_wr.adr.eq(self.bus_p.adr), p_row_wr.dat_w.eq(self.bus_p.dat_w),
            p_row_wr.we.eq(self.bus_p.we & idle), self.bus_p.dat_r.eq(p_mirror.dat_r),
            self.bus_kp.dat_r.eq(kp_rd.dat_r),
        ]

        self._pipeline(word_rd, tile_rd, p_own, p_mirror, idle)
        self._write_back(p_at_row, kp_rd, kp_wr, idle)

    # The word pipeline -------------------------------------------------------------------------

    def _pipeline(self, word_rd, tile_rd, p_own, p_mirror, idle):
        nb = self.node_bits
        wa = Signal(bits_for(self.words_depth + 1))
        tile = Signal(bits_for(self.tiles_depth + 1))
        issue = Signal()
        self.queue = queue = SyncFIFO(self._entry_width(), QUEUE_DEPTH)
        self.submodules += queue

        # F1: decode, in the tile context.
        decode = InstructionWord()
        self.submodules += decode
        f1_valid = Signal()
        row = Signal(nb)
        col_base = Signal(nb)
        mirror_col_base = Signal(nb)
        mirrored = Signal()
        next_row_base = Signal(nb)
        next_col_base = Signal(nb)
        next_mirrored = Signal()
        advance = Signal()
        self.comb += [
            decode.entry.eq(word_rd.dat_r),
            Cat(next_row_base, next_col_base, next_mirrored).eq(tile_rd.dat_r),
            advance.eq(f1_valid & decode.em),
        ]

        # F2 and the multipliers.
        f2 = dict(valid=Signal(), er=Signal(), flags=Signal(4), row=Signal(nb),
                  mirror_row=Signal(nb), mirrored=Signal(), value=Signal((VALUE_BITS, True)))
        own_mul = [Multiplier(VALUE_BITS, P_BITS) for _ in range(LANES)]
        mirror_mul = [Multiplier(VALUE_BITS, P_BITS) for _ in range(LANES)]
        self.submodules += own_mul + mirror_mul
        latency = own_mul[0].latency
        p_own_lanes, fill_own = lanes(p_own.dat_r, P_BITS)
        p_mirror_lanes, fill_mirror = lanes(p_mirror.dat_r, P_BITS)
        self.comb += fill_own + fill_mirror
        for lane in range(LANES):
            self.comb += [
                own_mul[lane].a.eq(f2["value"]), own_mul[lane].b.eq(p_own_lanes[lane]),
                mirror_mul[lane].a.eq(f2["value"]), mirror_mul[lane].b.eq(p_mirror_lanes[lane]),
            ]
        # The control of each word, delayed alongside the multipliers.
        control = Cat(f2["valid"], f2["er"], f2["flags"], f2["row"], f2["mirror_row"],
                      f2["mirrored"])
        delayed = [Signal(len(control)) for _ in range(latency)]
        self.sync += delayed[0].eq(control)
        for k in range(1, latency):
            self.sync += delayed[k].eq(delayed[k - 1])
        a = dict(valid=Signal(), er=Signal(), flags=Signal(4), row=Signal(nb),
                 mirror_row=Signal(nb), mirrored=Signal())
        self.comb += Cat(a["valid"], a["er"], a["flags"], a["row"], a["mirror_row"],
                         a["mirrored"]).eq(delayed[-1])

        # A: accumulate; E: an ER word's sums into the queue.
        own_acc = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        mirror_acc = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        fresh = Signal(reset=1)
        e = dict(valid=Signal(), flags=Signal(4), row=Signal(nb), mirror_row=Signal(nb),
                 mirrored=Signal())
        for lane in range(LANES):
            for acc, mul in ((own_acc[lane], own_mul[lane]), (mirror_acc[lane], mirror_mul[lane])):
                self.sync += If(a["valid"], If(fresh, acc.eq(mul.p)).Else(acc.eq(acc + mul.p)))
        self.sync += [
            If(a["valid"], fresh.eq(a["er"])),
            e["valid"].eq(a["valid"] & a["er"]),
            e["flags"].eq(a["flags"]), e["row"].eq(a["row"]),
            e["mirror_row"].eq(a["mirror_row"]), e["mirrored"].eq(a["mirrored"]),
        ]
        self.comb += [
            queue.din.eq(Cat(e["row"], e["mirror_row"], e["mirrored"], e["flags"],
                             *own_acc, *mirror_acc)),
            queue.we.eq(e["valid"]),
        ]

        # F0: fetch while the queue has room for every ER word that may be in flight.
        in_flight = 3 + latency + 1
        room = Signal()
        self.comb += room.eq(queue.level < QUEUE_DEPTH - in_flight)
        fsm = FSM(reset_state="IDLE")
        self.submodules.fsm = fsm
        fsm.act("IDLE",
            tile_rd.adr.eq(self.bus_tile.adr),
            word_rd.adr.eq(self.bus_word.adr),
            If(self.start & (self.length != 0),
                NextValue(fresh, 1), NextValue(self.stalls, 0),
                NextState("FIRST_TILE")))
        fsm.act("FIRST_TILE", tile_rd.adr.eq(0), NextState("SECOND_TILE"))
        fsm.act("SECOND_TILE",
            tile_rd.adr.eq(1),
            NextValue(tile, 0), NextValue(wa, 0),
            NextValue(row, next_row_base), NextValue(col_base, next_col_base),
            NextValue(mirror_col_base, self.last_row - next_col_base),
            NextValue(mirrored, next_mirrored),
            NextState("RUN"))
        fsm.act("RUN",
            tile_rd.adr.eq(tile + 1 + advance),
            word_rd.adr.eq(wa),
            issue.eq((wa != self.length) & room),
            If(issue, NextValue(wa, wa + 1)),
            If((wa != self.length) & ~room, NextValue(self.stalls, self.stalls + 1)),
            If(wa == self.length, NextState("DRAIN")))
        drained = Signal()
        fsm.act("DRAIN", If(drained, NextState("IDLE")))
        self.comb += self.busy.eq(~fsm.ongoing("IDLE"))

        # F1 -> F2 registers and the tile context.
        self.sync += [
            f1_valid.eq(issue),
            f2["valid"].eq(f1_valid),
            f2["er"].eq(decode.er),
            f2["flags"].eq(decode.flags),
            f2["row"].eq(row),
            f2["mirror_row"].eq(self.last_row - row),
            f2["mirrored"].eq(mirrored),
            f2["value"].eq(decode.value),
            If(advance,
                tile.eq(tile + 1),
                row.eq(next_row_base), col_base.eq(next_col_base),
                mirror_col_base.eq(self.last_row - next_col_base),
                mirrored.eq(next_mirrored),
            ).Elif(f1_valid & decode.er,
                row.eq(row + 1)),
        ]
        # The p reads of F1: p[col_base + c], p[n - 1 - col_base - c]; the array's while idle.
        self.comb += [
            If(idle,
                p_own.adr.eq(self.bus_p.adr), p_mirror.adr.eq(self.bus_p.adr),
            ).Else(
                p_own.adr.eq(col_base + decode.column),
                p_mirror.adr.eq(mirror_col_base - decode.column)),
        ]
        self._drained_parts = (drained, [f1_valid, f2["valid"], a["valid"], e["valid"]]
                               + [d[0] for d in delayed])

    def _entry_width(self):
        nb = self.node_bits
        return 2 * nb + 1 + 4 + 2 * LANES * SUM_BITS

    # The write-back and pᵀKp ---------------------------------------------------------------------

    def _write_back(self, p_at_row, kp_rd, kp_wr, idle):
        nb = self.node_bits
        queue = self.queue
        drained, in_pipe = self._drained_parts

        # The entry being written back.
        row = Signal(nb)
        mirror_row = Signal(nb)
        mirrored = Signal()
        flags = Signal(4)
        own = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        mirror = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        d_row = Signal(nb)
        d_mirror_row = Signal(nb)
        d_mirrored = Signal()
        d_flags = Signal(4)
        d_own = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        d_mirror = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        self.comb += Cat(d_row, d_mirror_row, d_mirrored, d_flags, *d_own, *d_mirror).eq(
            queue.dout)

        # The part in its update clock: which row, sums, first/last.
        part_row = Signal(nb)
        part_sums = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        part_first = Signal()
        part_last = Signal()
        updating = Signal()
        mirror_pending = Signal()

        # The pᵀKp sequencer: a job is p[row] (3 lanes) and the part's sums; it feeds the
        # multiplier one product per clock, lane by lane, low half then high half.
        job_p = [Signal((P_BITS, True)) for _ in range(LANES)]
        job_sums = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        left = Signal(3)      # products of the job still to feed
        step = Signal(3)      # 2·lane + half of the next one
        seq_busy = Signal()
        free_next = Signal()  # the sequencer can take a job in the next clock
        self.comb += [seq_busy.eq(left != 0), free_next.eq(left <= 1)]

        # Select: read Kp and p at the next part's row (the pending mirror part first).
        select_row = Signal(nb)
        take_own = Signal()
        take_mirror = Signal()
        self.comb += [
            take_mirror.eq(mirror_pending & ~updating & free_next),
            take_own.eq(~mirror_pending & ~updating & queue.readable & free_next),
            If(take_mirror, select_row.eq(mirror_row)).Else(select_row.eq(d_row)),
            queue.re.eq(take_own),
        ]
        self.comb += If(idle, kp_rd.adr.eq(self.bus_kp.adr)).Else(kp_rd.adr.eq(select_row))
        self.comb += p_at_row.adr.eq(select_row)
        self.sync += [
            updating.eq(take_own | take_mirror),
            If(take_own,
                row.eq(d_row), mirror_row.eq(d_mirror_row), mirrored.eq(d_mirrored),
                flags.eq(d_flags),
                *[o.eq(d) for o, d in zip(own, d_own)],
                *[m.eq(d) for m, d in zip(mirror, d_mirror)],
                mirror_pending.eq(d_mirrored),
                part_row.eq(d_row),
                part_first.eq(d_flags[FIRST_OWN]), part_last.eq(d_flags[LAST_OWN]),
                *[s.eq(d) for s, d in zip(part_sums, d_own)],
            ),
            If(take_mirror,
                mirror_pending.eq(0),
                part_row.eq(mirror_row),
                part_first.eq(flags[FIRST_MIRROR]), part_last.eq(flags[LAST_MIRROR]),
                *[s.eq(m) for s, m in zip(part_sums, mirror)],
            ),
        ]

        # Update: store or add, OR the magnitudes of a finished row, hand over to pᵀKp.
        old, fill_old = lanes(kp_rd.dat_r, SUM_BITS)
        p_lanes, fill_p = lanes(p_at_row.dat_r, P_BITS)
        new = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        self.comb += fill_old + fill_p
        for lane in range(LANES):
            self.comb += If(part_first, new[lane].eq(part_sums[lane])).Else(
                new[lane].eq(old[lane] + part_sums[lane]))
        self.comb += If(idle,
            kp_wr.adr.eq(self.bus_kp.adr), kp_wr.dat_w.eq(self.bus_kp.dat_w),
            kp_wr.we.eq(self.bus_kp.we),
        ).Else(
            kp_wr.adr.eq(part_row), kp_wr.dat_w.eq(Cat(*new)), kp_wr.we.eq(updating))
        self.sync += If(self.start & idle, *[o.eq(0) for o in self.kp_or]).Elif(
            updating & part_last,
            *[o.eq(o | magnitude(n)) for o, n in zip(self.kp_or, new)])
        self.sync += If(updating,
            step.eq(0), left.eq(Cat(0, self.directions)),
            *[j.eq(p) for j, p in zip(job_p, p_lanes)],
            *[j.eq(s) for j, s in zip(job_sums, part_sums)],
        ).Elif(seq_busy, step.eq(step + 1), left.eq(left - 1))

        # The products p · (low or high half of a sum), accumulated by half: a zero-extended
        # low half and a sign-extended high half, so Σ p·sum = Σ p·low + 2^32 · Σ p·high.
        mul = Multiplier(P_BITS, 33)
        self.submodules += mul
        lane_sel = Signal(2)
        high = Signal()
        chosen = Signal((SUM_BITS, True))
        low_half = Signal((33, True))
        high_half = Signal((32, True))
        self.comb += [
            lane_sel.eq(step[1:3]), high.eq(step[0]),
            chosen.eq(Array(job_sums)[lane_sel]),
            low_half.eq(chosen[0:32]),
            high_half.eq(chosen[32:64]),
            mul.a.eq(Array(job_p)[lane_sel]),
            If(high, mul.b.eq(high_half)).Else(mul.b.eq(low_half)),
            mul.valid_in.eq(seq_busy),
        ]
        tags = [Signal(3) for _ in range(mul.latency)]
        self.sync += tags[0].eq(step)
        for k in range(1, mul.latency):
            self.sync += tags[k].eq(tags[k - 1])
        out_tag = tags[-1]
        for lane in range(LANES):
            self.sync += If(self.start & idle,
                self.p_kp_low[lane].eq(0), self.p_kp_high[lane].eq(0),
            ).Elif(mul.valid & (out_tag[1:3] == lane),
                If(out_tag[0], self.p_kp_high[lane].eq(self.p_kp_high[lane] + mul.p)).Else(
                    self.p_kp_low[lane].eq(self.p_kp_low[lane] + mul.p)))

        # Done once nothing is in flight anywhere.
        self.comb += drained.eq(
            (Cat(*in_pipe) == 0) & ~queue.readable & ~updating & ~mirror_pending
            & ~seq_busy & ~mul.valid & ~self._mul_in_flight(mul))

    def _mul_in_flight(self, mul):
        """True while any product is inside the pᵀKp multiplier's pipeline."""
        flight = Signal(mul.latency)
        self.sync += flight.eq(Cat(mul.valid_in, flight[0:mul.latency - 1]))
        return flight != 0
