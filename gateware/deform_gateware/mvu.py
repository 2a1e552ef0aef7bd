"""One matrix-vector unit (thesis 4.2.1, Fig. 4-6): Kp = K·p for up to three fused directions,
one instruction word per clock, with its row write-backs, pᵀKp and max |Kp|.

What it computes is ``target-core``'s portable kernel (``kernel::portable_row``,
``kernel::p_kp_and_max``) bit for bit; how its memories are filled is
``target-core/src/mvu_program.rs``.

Memories (all loaded between phases by the MVU array's bus; the unit only reads them, except Kp):

- ``words`` (block RAM): 36-bit entries, the instruction words of its tiles back to back and
  the write-back flags of each ER word (``word.FIRST_OWN`` ...);
- ``tiles`` (``tile_table.TileTable``, distributed RAM read in tile order): per tile
  ``row_base``, ``col_base``, ``n - 1 - col_base`` and the mirrored bit; EM moves to the next
  one. The next tile's header waits in a register (``header``) and the table's cursor is one
  tile further ahead, its entry shown from registers, so an EM loads the tile context from a
  register and ``header`` from a 2-way select of registers; the table's read ends in the
  table's own registers, not in the unit's;
- ``p_col`` (block RAM): p (three 32-bit lanes per node), read twice per clock: at column
  ``col_base + c`` and, for a mirrored tile, at ``n - 1 - col_base - c``;
- ``p_row`` (block RAM): another copy of p, read at the row of each write-back (for pᵀKp);
- ``kp`` (block RAM): this unit's Kp, three 64-bit sums per row.

Every block RAM read answers two clocks after its address (``bram.LATENCY``: the block's output
register is on, which is what lets the unit run at the thesis's 133 MHz on an ECP5).

The word pipeline (no stage ever stalls; the fetch waits instead):

    F0  fetch the word memory at ``wa``
    F1  (block RAM)
    F2  decode EM/ER/column/value/flags, in the tile context
    F3  the p addresses, registered (``col_base + c``, ``n - 1 - col_base - c``)
    F4  (block RAM)
    F5  p is there: the multipliers take value x p for 3 lanes, own and mirrored
    M.. the multipliers' pipeline (``Multiplier.latency`` clocks; on the ECP5 the DSP blocks'
        own input and output registers are two of them)
    A   accumulate, 64 bits per lane; an ER word's sums are complete after it
    E   an ER word's sums (and rows, flags) go into the write-back queue

The write-back queue (``write_back_queue.WriteBackQueue``) has its head in a register and decides
its memory's pop from registers beside it. The write-back takes queue entries one part at a time (the own row, then the mirror row of a
mirrored tile) into a register, S, and from there through W (read Kp and p at the row), W2
(their data registered beside the adders), U (store the first write-back of the row in this
phase, or add) and R (write Kp, OR the magnitudes into max |Kp| if this was the row's last
write-back). U hands p[row] and the sums to the pᵀKp sequencer, which multiplies each lane's
32-bit p by the sum's low and high halves in turn (2 clocks per direction) and accumulates
Σ p·low and Σ p·high; the array joins them into pᵀKp. A part leaves S at most every other
clock, never onto a row still being written nor before the sequencer can take its job; the
decision is an AND of registers (the queue's pop, the row compares and the sequencer's count
are each made a clock ahead), not the long path from the queue's memory to its own pop that it
was. The fetch stops while the queue could overflow (its room, too, is decided a clock ahead,
with one entry more in reserve); ``stalls`` counts those clocks.

A phase: IDLE, HEADER (tile 0's header into ``header``), FIRST_TILE, RUN (one word fetched per
clock), DRAIN (until nothing is in flight: ``drained``, a register, so a clock late). ``busy``
is a register set and cleared with the state's own transitions, not a decode of the state; what
a start resets or loads (``fresh``, the tile context) hangs on ``go``, the start's
decode as a register of its own (a clock after ``start``, in HEADER), not on the state's.
"""

from types import SimpleNamespace

from migen import (Module, Signal, Array, Cat, If, FSM, NextState, NextValue,
                   Replicate)

from deform_gateware.bram import Bram, LATENCY
from deform_gateware.multiplier import Multiplier
from deform_gateware.tile_table import TileTable
from deform_gateware.write_back_queue import WriteBackQueue
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
    """The side of a memory the MVU array drives while the unit is idle (reads answer
    ``bram.LATENCY`` clocks after the address, the tile table's in the same clock)."""

    def __init__(self, adr_bits, width):
        self.adr = Signal(adr_bits)
        self.dat_r = Signal(width)
        self.dat_w = Signal(width)
        self.we = Signal()


class Mvu(Module):
    """One MVU: ``words`` word entries, ``tiles`` tiles, p and Kp for ``nodes`` rows;
    ``primitive``: ECP5 block RAM primitives (see ``bram``)."""

    def __init__(self, words, tiles, nodes, primitive=False):
        self.words_depth, self.tiles_depth, self.nodes_depth = words, tiles, nodes
        self.primitive = primitive
        nb = bits_for(nodes)
        self.node_bits = nb

        # Set by the array.
        self.start = Signal()
        self.last_row = Signal(nb)              # n - 1
        self.directions = Signal(2)             # 1..3
        self.length = Signal(bits_for(words + 1))  # words to run (0: sit the phase out)
        # Status and results. `busy` is "not in IDLE", a register of its own beside the state:
        # it selects every memory port between the array's bus and the unit, so it fans out
        # across the whole unit, and a decode of the state in front of it was a critical path.
        self.busy = Signal()
        self.stalls = Signal(32)  # clocks the fetch waited, over every phase since reset
        self.p_kp_low = [Signal((HALF_SUM_BITS, True)) for _ in range(LANES)]
        self.p_kp_high = [Signal((HALF_SUM_BITS, True)) for _ in range(LANES)]
        self.kp_or = [Signal(SUM_BITS) for _ in range(LANES)]

        # Memories, and the ports the array uses while the unit is idle.
        self.submodules.words = Bram(ENTRY_BITS, words, primitive=primitive)
        self.submodules.p_col = Bram(LANES * P_BITS, nodes, read_ports=2, primitive=primitive)
        self.submodules.p_row = Bram(LANES * P_BITS, nodes, primitive=primitive)
        self.submodules.kp = Bram(LANES * SUM_BITS, nodes, primitive=primitive)
        self.submodules.tiles = TileTable(3 * nb + 1, tiles)
        self.bus_word = BusPort(bits_for(words), ENTRY_BITS)
        self.bus_tile = BusPort(bits_for(tiles), 3 * nb + 1)   # write only
        self.bus_p = BusPort(nb, LANES * P_BITS)   # writes both copies, reads p_col
        self.bus_kp = BusPort(nb, LANES * SUM_BITS)

        idle = ~self.busy
        self.comb += [
            self.words.adr.eq(self.bus_word.adr), self.words.dat_w.eq(self.bus_word.dat_w),
            self.words.we.eq(self.bus_word.we & idle),
            self.bus_word.dat_r.eq(self.words.read[0].dat),
            self.tiles.adr.eq(self.bus_tile.adr), self.tiles.dat_w.eq(self.bus_tile.dat_w),
            self.tiles.we.eq(self.bus_tile.we & idle), self.tiles.rewind.eq(idle),
            self.p_col.adr.eq(self.bus_p.adr), self.p_col.dat_w.eq(self.bus_p.dat_w),
            self.p_col.we.eq(self.bus_p.we & idle),
            self.p_row.adr.eq(self.bus_p.adr), self.p_row.dat_w.eq(self.bus_p.dat_w),
            self.p_row.we.eq(self.bus_p.we & idle),
            self.bus_p.dat_r.eq(self.p_col.read[1].dat),
            self.bus_kp.dat_r.eq(self.kp.read[0].dat),
        ]
        # The word pipeline, stage by stage, then the write-back. The builders are called from
        # here, one after another, in the order the signals were always made in, and hand their
        # signals on in `pipe` and `wb`: Migen names a signal after the variable that holds it
        # and the `self` frames it was made in, and orders its Verilog by when it was made, so a
        # builder called from another builder, or another order, would rename or reorder the
        # Verilog.
        pipe = SimpleNamespace()
        self._decode(pipe)
        self._multiply(pipe)
        self._accumulate(pipe)
        self._fetch(pipe)
        self._tile_context(pipe, idle)
        wb = SimpleNamespace()
        self._queue_head(wb)
        self._write_back_stages(wb)
        self._take_part(wb, idle)
        self._update_row(wb, idle)
        self._p_kp(wb, idle)
        self._drained(pipe, wb)

    # The word pipeline -------------------------------------------------------------------------

    def _decode(self, pipe):
        """F2: the fetched entry decoded (EM, ER, column, value, flags) in its tile's context
        (``row``, ``col_base``, ``mirror_col_base``, ``mirrored``), with the next tile's header
        waiting in ``header`` so that an EM word moves the context on from registers
        (``advance``; ``_tile_context`` moves it). The fetch's word address and issue
        (``_fetch`` drives them) and the write-back queue are made here first, where they always
        were made (see ``__init__``)."""
        nb = self.node_bits
        wa = Signal(bits_for(self.words_depth + 1))
        issue = Signal()
        # The write-back queue: its head a register (the memory's read is registered), so that
        # what the write-back decides from it starts at a register, not at a memory read.
        self.queue = queue = WriteBackQueue(self._entry_width(), QUEUE_DEPTH)
        self.submodules += queue

        # F2: decode, in the tile context; `header` holds the next tile's header and the tile
        # table's cursor is at the one after it.
        decode = InstructionWord()
        self.submodules += decode
        fetched = [Signal() for _ in range(LATENCY)]   # F1, F2 valid
        f2_valid = fetched[-1]
        row = Signal(nb)
        col_base = Signal(nb)
        mirror_col_base = Signal(nb)
        mirrored = Signal()
        next_row_base = Signal(nb)
        next_col_base = Signal(nb)
        next_mirror_col_base = Signal(nb)
        next_mirrored = Signal()
        header = Signal(len(self.tiles.dat))
        advance = Signal()
        self.comb += [
            decode.entry.eq(self.words.read[0].dat),
            Cat(next_row_base, next_col_base, next_mirror_col_base, next_mirrored).eq(header),
            advance.eq(f2_valid & decode.em),
        ]
        pipe.wa, pipe.issue, pipe.decode, pipe.fetched = wa, issue, decode, fetched
        pipe.f2_valid, pipe.header, pipe.advance = f2_valid, header, advance
        pipe.row, pipe.col_base = row, col_base
        pipe.mirror_col_base, pipe.mirrored = mirror_col_base, mirrored
        pipe.next_tile = (next_row_base, next_col_base, next_mirror_col_base, next_mirrored)

    def _multiply(self, pipe):
        """F3..F5 and the multipliers: the two p addresses of a word registered at F3 (its
        column in the tile, own and mirrored), p from the block RAM at F5 into value x p for
        three lanes, own and mirrored (``Multiplier.latency`` clocks); the word's control
        travels alongside, in registers, out to ``a`` (stage A)."""
        nb = self.node_bits
        decode, f2_valid, row, mirrored = pipe.decode, pipe.f2_valid, pipe.row, pipe.mirrored
        col_base, mirror_col_base = pipe.col_base, pipe.mirror_col_base
        # F3..F5: the p addresses, registered at F3, then the block RAM; p is there at F5. The
        # word's control and value travel alongside.
        control_bits = 1 + 1 + 4 + 2 * nb + 1
        mirror_row = Signal(nb)
        self.comb += mirror_row.eq(self.last_row - row)
        f = [(Signal(control_bits), Signal((VALUE_BITS, True))) for _ in range(1 + LATENCY)]
        self.sync += [
            f[0][0].eq(Cat(f2_valid, decode.er, decode.flags, row, mirror_row, mirrored)),
            f[0][1].eq(decode.value),
            *[dst.eq(src) for k in range(1, len(f)) for dst, src in zip(f[k], f[k - 1])],
        ]
        last_control, last_value = f[-1]
        p_own_adr = Signal(nb)
        p_mirror_adr = Signal(nb)
        self.sync += [p_own_adr.eq(col_base + decode.column),
                      p_mirror_adr.eq(mirror_col_base - decode.column)]
        own_mul = [Multiplier(VALUE_BITS, P_BITS, self.primitive) for _ in range(LANES)]
        mirror_mul = [Multiplier(VALUE_BITS, P_BITS, self.primitive) for _ in range(LANES)]
        self.submodules += own_mul + mirror_mul
        latency = own_mul[0].latency
        p_own_lanes, fill_own = lanes(self.p_col.read[0].dat, P_BITS)
        p_mirror_lanes, fill_mirror = lanes(self.p_col.read[1].dat, P_BITS)
        self.comb += fill_own + fill_mirror
        for lane in range(LANES):
            self.comb += [
                own_mul[lane].a.eq(last_value), own_mul[lane].b.eq(p_own_lanes[lane]),
                mirror_mul[lane].a.eq(last_value), mirror_mul[lane].b.eq(p_mirror_lanes[lane]),
            ]
        # The control of each word, delayed alongside the multipliers.
        delayed = [Signal(control_bits) for _ in range(latency)]
        self.sync += delayed[0].eq(last_control)
        for k in range(1, latency):
            self.sync += delayed[k].eq(delayed[k - 1])
        a = dict(valid=Signal(), er=Signal(), flags=Signal(4), row=Signal(nb),
                 mirror_row=Signal(nb), mirrored=Signal())
        self.comb += Cat(a["valid"], a["er"], a["flags"], a["row"], a["mirror_row"],
                         a["mirrored"]).eq(delayed[-1])
        pipe.f, pipe.p_own_adr, pipe.p_mirror_adr = f, p_own_adr, p_mirror_adr
        pipe.own_mul, pipe.mirror_mul, pipe.latency = own_mul, mirror_mul, latency
        pipe.delayed, pipe.a = delayed, a

    def _accumulate(self, pipe):
        """A and E: the products summed into 64-bit accumulators per lane, own and mirrored,
        a row's first word storing rather than adding (``fresh``); an ER word's sums, rows
        and flags into the write-back queue a clock later. Also makes ``go``, a phase's start
        as a register, which sets ``fresh`` (and, in ``_tile_context``, loads tile 0)."""
        nb = self.node_bits
        queue, own_mul, mirror_mul, a = self.queue, pipe.own_mul, pipe.mirror_mul, pipe.a
        # `go`: a phase starts (the start's decode, from the inputs and `busy`, as a register of
        # its own, a clock after `start`); it sets `fresh`.
        go = Signal()
        self.sync += go.eq(self.start & ~self.busy & (self.length != 0))

        # A: accumulate; E: an ER word's sums into the queue.
        own_acc = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        mirror_acc = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        fresh = Signal(reset=1)
        e = dict(valid=Signal(), flags=Signal(4), row=Signal(nb), mirror_row=Signal(nb),
                 mirrored=Signal())
        for lane in range(LANES):
            for acc, mul in ((own_acc[lane], own_mul[lane]), (mirror_acc[lane], mirror_mul[lane])):
                self.sync += If(a["valid"], If(fresh, acc.eq(mul.p)).Else(acc.eq(acc + mul.p)))
        # A phase's first word starts a row: `fresh` is set by `go` (a clock after the start, in
        # HEADER, long before a word reaches A), not by the state's decode: `fresh` selects all
        # 384 accumulator bits, so it sits among them, far from the state, and that decode
        # routed to it was a critical path.
        self.sync += [
            If(go, fresh.eq(1)).Elif(a["valid"], fresh.eq(a["er"])),
            e["valid"].eq(a["valid"] & a["er"]),
            e["flags"].eq(a["flags"]), e["row"].eq(a["row"]),
            e["mirror_row"].eq(a["mirror_row"]), e["mirrored"].eq(a["mirrored"]),
        ]
        self.comb += [
            queue.din.eq(Cat(e["row"], e["mirror_row"], e["mirrored"], e["flags"],
                             *own_acc, *mirror_acc)),
            queue.we.eq(e["valid"]),
        ]
        pipe.go, pipe.e = go, e

    def _fetch(self, pipe):
        """F0 and the phase's state machine: one word fetched per clock while the queue has
        room for every ER word that may be in flight (``room``, a register, decided a clock
        ahead); ``stalls`` counts the clocks it waited, over every phase since reset. Makes
        ``drained`` (the write-back drives it)."""
        queue, wa, issue = self.queue, pipe.wa, pipe.issue
        f, latency = pipe.f, pipe.latency
        # F0: fetch while the queue has room for every ER word that may be in flight.
        # (F1, F2, F3..F5, the multipliers, E, and the word being fetched.)
        # `room` is a register, made from the level of the clock before: the queue's level (its
        # memory's count plus the head register) and the compare are then no path into the
        # fetch's registers (`wa`, `at_end`, `stalls`). The level may have grown by one since,
        # so the bound keeps one entry more in reserve.
        in_flight = LATENCY + len(f) + latency + 2
        room = Signal()
        self.sync += room.eq(queue.level < QUEUE_DEPTH - in_flight - 1)
        fsm = FSM(reset_state="IDLE")
        self.submodules.fsm = fsm
        fsm.act("IDLE",
            self.words.read[0].adr.eq(self.bus_word.adr),
            If(self.start & (self.length != 0),
                NextValue(self.busy, 1),
                NextState("HEADER")))
        fsm.act("HEADER", NextState("FIRST_TILE"))    # tile 0's header into `header` (at `go`)
        # `at_end` is `wa == length`, a register of its own (made from wa's next value): the
        # compare of the word address is then no path into the state register, which fans out
        # to every memory's port multiplexer and sits far from the fetch.
        at_end = Signal()
        stalled = Signal()    # RUN, and no room for the next word
        fsm.act("FIRST_TILE",  # tile 0's context from `header`, tile 1's header into it
            NextValue(wa, 0), NextValue(at_end, 0),
            NextState("RUN"))
        fsm.act("RUN",
            self.words.read[0].adr.eq(wa),
            issue.eq(~at_end & room),
            If(issue, NextValue(wa, wa + 1), NextValue(at_end, wa + 1 == self.length)),
            stalled.eq(~at_end & ~room),
            If(at_end, NextState("DRAIN")))
        # `stalls` counts a clock late, from a register (`stalled` of the clock before), over
        # every phase since reset (the firmware reads it when a matrix is loaded and dropped):
        # its 32 enables hang on a register only, no decode of the state (that path was a
        # critical one).
        stalled_before = Signal()
        self.sync += [
            stalled_before.eq(stalled),
            If(stalled_before, self.stalls.eq(self.stalls + 1)),
        ]
        drained = Signal()
        fsm.act("DRAIN", If(drained, NextValue(self.busy, 0), NextState("IDLE")))
        pipe.drained = drained

    def _tile_context(self, pipe, idle):
        """F1/F2's valid bits, the tile context moved at an EM word (and twice at a start, from
        ``go``), ``row`` counted on at an ER word, and the p reads of F3 (the array's
        address while the unit is idle)."""
        go, advance, fetched, f2_valid = pipe.go, pipe.advance, pipe.fetched, pipe.f2_valid
        decode, header, row, col_base = pipe.decode, pipe.header, pipe.row, pipe.col_base
        mirror_col_base, mirrored = pipe.mirror_col_base, pipe.mirrored
        next_row_base, next_col_base, next_mirror_col_base, next_mirrored = pipe.next_tile
        issue, p_own_adr, p_mirror_adr = pipe.issue, pipe.p_own_adr, pipe.p_mirror_adr
        # F0 -> F2 valid bits, and the tile context at F2. The context moves to the next tile
        # at an EM word, and twice at a start, from registers (`go` and `go` a clock later, in
        # HEADER and FIRST_TILE: tile 0's header into `header`, then into the context), so no
        # decode of the state drives these enables.
        go_before = Signal()
        shift = Signal()
        self.comb += [shift.eq(advance | go | go_before), self.tiles.shift.eq(shift)]
        self.sync += [
            go_before.eq(go),
            fetched[0].eq(issue),
            *[fetched[k].eq(fetched[k - 1]) for k in range(1, LATENCY)],
            If(shift,
                header.eq(self.tiles.dat),
                row.eq(next_row_base), col_base.eq(next_col_base),
                mirror_col_base.eq(next_mirror_col_base),
                mirrored.eq(next_mirrored),
            ).Elif(f2_valid & decode.er,
                row.eq(row + 1)),
        ]
        # The p reads of F3: p[col_base + c], p[n - 1 - col_base - c]; the array's while idle.
        self.comb += [
            If(idle,
                self.p_col.read[0].adr.eq(self.bus_p.adr),
                self.p_col.read[1].adr.eq(self.bus_p.adr),
            ).Else(
                self.p_col.read[0].adr.eq(p_own_adr),
                self.p_col.read[1].adr.eq(p_mirror_adr)),
        ]

    def _entry_width(self):
        nb = self.node_bits
        return 2 * nb + 1 + 4 + 2 * LANES * SUM_BITS

    # The write-back and pᵀKp ---------------------------------------------------------------------

    def _queue_head(self, wb):
        """The write-back queue's head unpacked (``d_*``: rows, flags, own and mirrored sums of
        an ER word), and the registers that keep an entry's mirror part while its own part goes
        first (``mirror_row``, ``flags``, ``mirror``, ``mirror_pending``)."""
        nb = self.node_bits
        queue = self.queue

        # The queue's head, and the entry whose mirror part is still to go.
        d_row = Signal(nb)
        d_mirror_row = Signal(nb)
        d_mirrored = Signal()
        d_flags = Signal(4)
        d_own = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        d_mirror = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        self.comb += Cat(d_row, d_mirror_row, d_mirrored, d_flags, *d_own, *d_mirror).eq(
            queue.dout)
        mirror_row = Signal(nb)
        flags = Signal(4)
        mirror = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        mirror_pending = Signal()
        wb.d_row, wb.d_mirror_row, wb.d_mirrored = d_row, d_mirror_row, d_mirrored
        wb.d_flags, wb.d_own, wb.d_mirror = d_flags, d_own, d_mirror
        wb.mirror_row, wb.flags, wb.mirror = mirror_row, flags, mirror
        wb.mirror_pending = mirror_pending

    def _write_back_stages(self, wb):
        """The registers of a part in each write-back stage (S, W, W2, U, R), and the pᵀKp
        sequencer's job, count and ``free_soon``: whether a part leaving S now finds the
        sequencer ready to take its job when it reaches U, LATENCY + 1 clocks later."""
        nb = self.node_bits
        # A part (a row, its sums, first/last) through the stages S (the next part, in a
        # register of its own), W and W2 (Kp and p read at its row: the block RAMs, then a
        # register of their data beside the adders, which the block may be placed far from),
        # U (update: store or add) and R (write Kp, OR the magnitudes of a finished row). A part
        # may not leave S while a part ahead of it has yet to write its row, nor while a part
        # is in W (its pᵀKp job would be due in the same clock), so parts leave S at most every
        # other clock; S refills in the clock between. Every input of that decision is a
        # register: the pop of the queue, the row compares and the sequencer's count each
        # happen a clock ahead.
        def part():
            return dict(valid=Signal(), row=Signal(nb), first=Signal(), last=Signal(),
                        sums=[Signal((SUM_BITS, True)) for _ in range(LANES)])
        s, w, w2, u, r = part(), part(), part(), part(), part()

        # The pᵀKp sequencer: a job is p[row] (3 lanes) and the part's sums; it feeds the
        # multiplier one product per clock, lane by lane, low half then high half.
        job_p = [Signal((P_BITS, True)) for _ in range(LANES)]
        job_sums = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        left = Signal(3)      # products of the job still to feed
        step = Signal(3)      # 2·lane + half of the next one
        seq_busy = Signal()
        # A part leaving S now reaches U (and hands over its job) LATENCY + 1 clocks later, when
        # the sequencer must be feeding its last product at the latest: with a part in W2 or U
        # (it hands over its job of 2·directions products first) only one direction allows
        # that, else at most LATENCY + 2 products may be left. `free_soon` says so for this
        # clock, computed in the clock before from what `left` and the valid bits become.
        free_soon = Signal(reset=1)
        left_next = Signal(3)
        job = Cat(0, self.directions)      # 2·directions products
        self.comb += [
            seq_busy.eq(left != 0),
            If(u["valid"], left_next.eq(job)).Elif(seq_busy, left_next.eq(left - 1)).Else(
                left_next.eq(left)),
        ]
        self.sync += If(w["valid"] | w2["valid"], free_soon.eq(self.directions == 1)).Else(
            free_soon.eq(left_next <= LATENCY + 2))
        wb.s, wb.w, wb.w2, wb.u, wb.r = s, w, w2, u, r
        wb.job_p, wb.job_sums, wb.left, wb.step = job_p, job_sums, left, step
        wb.seq_busy, wb.free_soon = seq_busy, free_soon

    def _take_part(self, wb, idle):
        """S: the next part (the pending mirror part, else the queue's head) and when it may
        leave for W (``take``: no row hazard with W2, U or R, no part in W, the sequencer
        free soon), every input of that a register; then W, W2, U carry it on while Kp and
        p are read at its row."""
        nb = self.node_bits
        queue, kp_rd, p_at_row = self.queue, self.kp.read[0], self.p_row.read[0]
        s, w, w2, u = wb.s, wb.w, wb.w2, wb.u
        mirror_row, flags, mirror, mirror_pending = (wb.mirror_row, wb.flags, wb.mirror,
                                                     wb.mirror_pending)
        d_row, d_mirror_row, d_mirrored, d_flags = (wb.d_row, wb.d_mirror_row, wb.d_mirrored,
                                                    wb.d_flags)
        d_own, d_mirror, free_soon = wb.d_own, wb.d_mirror, wb.free_soon
        # S refills while empty: the mirror part of the entry taken last, else the queue's head.
        load = Signal()
        take = Signal()
        wants_head = Signal(reset=1)
        # S's row twice: `s["row"]` for the row compares and W, and its complement `s_row_n` for
        # the address pins of the ~17 block RAMs of Kp and p at the row, which pulled the one
        # register far from the compares (a critical path; complemented, so that Yosys does not
        # merge the two registers).
        s_row_n = Signal(nb, reset=(1 << nb) - 1)
        hazard = Signal()     # S's row is that of the part in W2, U or R
        # The row S holds in the next clock is one of three candidates (S's own, the pending
        # mirror row, the queue head's); each is compared with W, W2 and U on its own and the
        # select comes last, so `mirror_pending` (placed among the wide S and mirror registers
        # it selects) drives one LUT before `hazard`, not the row multiplexer and the compares.
        def conflicts(candidate):
            return Cat(*[x["valid"] & (x["row"] == candidate) for x in (w, w2, u)]) != 0
        self.comb += [
            load.eq(~s["valid"] & (mirror_pending | queue.readable)),
            queue.re.eq(wants_head),
            take.eq(s["valid"] & ~hazard & ~w["valid"] & free_soon),
        ]
        # `wants_head` is ~S.valid & ~mirror_pending, as a register of its own, made from their
        # next values: those two sit among the ~200 S and mirror bits they select, far from the
        # queue, and the queue's pop (its memory's read enable and level counter) hung on them
        # through a LUT placed among them, a critical path out to them and back.
        self.sync += If(~s["valid"], wants_head.eq(~load)).Elif(take,
            wants_head.eq(~mirror_pending)).Else(wants_head.eq(0))
        self.sync += [
            If(s["valid"], hazard.eq(conflicts(s["row"]))).Elif(mirror_pending,
                hazard.eq(conflicts(mirror_row))).Else(hazard.eq(conflicts(d_row))),
            If(~s["valid"],
                s["valid"].eq(load),
                If(mirror_pending,
                    mirror_pending.eq(0),
                    s["row"].eq(mirror_row), s_row_n.eq(~mirror_row),
                    s["first"].eq(flags[FIRST_MIRROR]), s["last"].eq(flags[LAST_MIRROR]),
                    *[x.eq(m) for x, m in zip(s["sums"], mirror)],
                ).Else(
                    mirror_pending.eq(queue.readable & d_mirrored),
                    mirror_row.eq(d_mirror_row), flags.eq(d_flags),
                    *[m.eq(d) for m, d in zip(mirror, d_mirror)],
                    s["row"].eq(d_row), s_row_n.eq(~d_row),
                    s["first"].eq(d_flags[FIRST_OWN]), s["last"].eq(d_flags[LAST_OWN]),
                    *[x.eq(d) for x, d in zip(s["sums"], d_own)],
                ),
            ).Elif(take, s["valid"].eq(0)),
        ]
        self.comb += If(idle, kp_rd.adr.eq(self.bus_kp.adr)).Else(kp_rd.adr.eq(~s_row_n))
        self.comb += p_at_row.adr.eq(~s_row_n)
        self.sync += [
            w["valid"].eq(take), w["row"].eq(s["row"]), w["first"].eq(s["first"]),
            w["last"].eq(s["last"]), *[x.eq(y) for x, y in zip(w["sums"], s["sums"])],
            *[st for a, b in ((w, w2), (w2, u)) for st in
              [b["valid"].eq(a["valid"]), b["row"].eq(a["row"]), b["first"].eq(a["first"]),
               b["last"].eq(a["last"]), *[x.eq(y) for x, y in zip(b["sums"], a["sums"])]]],
        ]

    def _update_row(self, wb, idle):
        """U and R: the part's sums stored (a row's first write-back in the phase) or added to
        Kp as read, written back at R, and a finished row's magnitudes ORed into max |Kp|;
        at U the part's job (p[row] and its sums) goes to the pᵀKp sequencer."""
        kp_rd, p_at_row = self.kp.read[0], self.p_row.read[0]
        u, r, seq_busy, step, left = wb.u, wb.r, wb.seq_busy, wb.step, wb.left
        job_p, job_sums = wb.job_p, wb.job_sums
        # U: store or add (Kp and p at the row have arrived), and hand over to pᵀKp.
        kp_at_u = Signal(len(kp_rd.dat))
        p_at_u = Signal(len(p_at_row.dat))
        self.sync += [kp_at_u.eq(kp_rd.dat), p_at_u.eq(p_at_row.dat)]
        old, fill_old = lanes(kp_at_u, SUM_BITS)
        p_lanes, fill_p = lanes(p_at_u, P_BITS)
        self.comb += fill_old + fill_p
        self.sync += [
            r["valid"].eq(u["valid"]), r["row"].eq(u["row"]), r["last"].eq(u["last"]),
            *[If(u["first"], x.eq(s)).Else(x.eq(o + s))
              for x, o, s in zip(r["sums"], old, u["sums"])],
        ]
        # R: write, and OR the magnitudes of a finished row.
        self.comb += If(idle,
            self.kp.adr.eq(self.bus_kp.adr), self.kp.dat_w.eq(self.bus_kp.dat_w),
            self.kp.we.eq(self.bus_kp.we),
        ).Else(
            self.kp.adr.eq(r["row"]), self.kp.dat_w.eq(Cat(*r["sums"])),
            self.kp.we.eq(r["valid"]))
        self.sync += If(self.start & idle, *[o.eq(0) for o in self.kp_or]).Elif(
            r["valid"] & r["last"],
            *[o.eq(o | magnitude(n)) for o, n in zip(self.kp_or, r["sums"])])
        self.sync += If(u["valid"],
            step.eq(0), left.eq(Cat(0, self.directions)),
            *[j.eq(p) for j, p in zip(job_p, p_lanes)],
            *[j.eq(x) for j, x in zip(job_sums, u["sums"])],
        ).Elif(seq_busy, step.eq(step + 1), left.eq(left - 1))

    def _p_kp(self, wb, idle):
        """pᵀKp: the sequencer's products p · (low or high half of a sum), one per clock
        through one multiplier, each tagged with its lane and half, and accumulated by half
        into ``p_kp_low`` and ``p_kp_high`` (cleared at a start)."""
        step, job_p, job_sums, seq_busy = wb.step, wb.job_p, wb.job_sums, wb.seq_busy
        # The products p · (low or high half of a sum), accumulated by half: a zero-extended
        # low half and a sign-extended high half, so Σ p·sum = Σ p·low + 2^32 · Σ p·high.
        mul = Multiplier(P_BITS, 33, self.primitive)
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
        wb.mul = mul

    def _drained(self, pipe, wb):
        """``drained``: nothing in flight anywhere, from the word pipeline's valid bits to the
        pᵀKp multiplier; the state machine's DRAIN waits for it."""
        queue, drained, mul = self.queue, pipe.drained, wb.mul
        mirror_pending, seq_busy = wb.mirror_pending, wb.seq_busy
        s, w, w2, u, r = wb.s, wb.w, wb.w2, wb.u, wb.r
        fetched, f, a, e, delayed = pipe.fetched, pipe.f, pipe.a, pipe.e, pipe.delayed
        in_pipe = (fetched + [c[0] for c, _ in f] + [a["valid"], e["valid"]]
                   + [d[0] for d in delayed])
        stages = [s["valid"], w["valid"], w2["valid"], u["valid"], r["valid"]]

        # Done once nothing is in flight anywhere; a register, a clock late (in DRAIN nothing
        # enters the pipeline, so what was empty stays empty): this wide AND is then no path
        # into the state register. The queue counts as empty from its head's valid bit and its
        # memory's count, not from `level`, their sum (a carry chain that was a critical path).
        self.sync += drained.eq(
            (Cat(*in_pipe, *stages) == 0) & ~queue.readable & (queue.fifo.level == 0)
            & ~mirror_pending
            & ~seq_busy & ~mul.valid & ~self._mul_in_flight(mul))

    def _mul_in_flight(self, mul):
        """True while any product is inside the pᵀKp multiplier's pipeline."""
        flight = Signal(mul.latency)
        self.sync += flight.eq(Cat(mul.valid_in, flight[0:mul.latency - 1]))
        return flight != 0
