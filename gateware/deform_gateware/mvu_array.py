"""The MVUs side by side (thesis Fig. 4-8): their shared p and Kp as memory the CPU addresses,
the phase's control and status registers, the reduction of rows that several MVUs write, and
the bus that loads each MVU's program.

One Wishbone region (``REGION_SIZE`` bytes, uncached on the VexRiscv) holds, at these byte
offsets (also written into csr.json as constants, ``MVUS_*_OFFSET``, for the firmware):

- ``P_OFFSET``: p, 16 bytes per node, lanes 0..2 the three directions' mantissas and lane 3 the
  padding (``kernel::Lanes``). A write goes to every MVU's copies; a read comes from MVU 0's.
- ``KP_OFFSET``: Kp, 24 bytes per row (``kernel::Sums``: three little-endian i64). A row is read
  from and written to its owner's Kp memory (``OWNER_OFFSET``), or MVU 0's in plain mode.
- ``OWNER_OFFSET``: one word per row, the owner MVU. ``SHARED_OFFSET``: the shared-rows list,
  one word per entry (row in bits 0..15, contributor mask in 16..23, owner in 24..26).
- ``UNIT_OFFSET + m * UNIT_STRIDE``: MVU m: its word memory (8 bytes per entry: the word, then
  the flags in bits 0..3), its tile table at ``UNIT_TILES`` (8 bytes per tile: row_base in
  bits 0..15 and col_base in 16..31, then n - 1 - col_base in bits 0..15 and the mirrored bit
  in bit 31; written first word first, the entry is stored when its second word arrives, and
  reads as 0), and its word count at ``UNIT_LENGTH``.

All of this layout is ``target-core/src/mvu_program.rs``'s, and p and Kp are exactly the
solver's ``p: &mut [Lanes]`` and ``kp: &mut [Sums]``: the firmware lends these windows to the
solver as its vectors, so that no vector is copied in or out per iteration. Every access is
read-modify-write of a whole memory entry (byte enables honoured), so the windows behave as
RAM. The CPU waits (no acknowledge) while a phase runs.

A phase (``start``): every MVU with words runs its tiles; then the shared rows are summed into
their owners (one MVU per clock) and ORed into max |Kp|; then the MVUs' Σ p·low, Σ p·high and
ORs are summed (one MVU per clock) into ``p_kp*`` and ``kp_or*``. ``phases`` counts the
phases, ``cycles`` their clocks and ``stalls`` the clocks MVU 0's fetch waited for its
write-back, all since reset (wrapping at 2^32): the firmware reads them when it loads and
drops a matrix, not in every phase, where two CSR reads and the sums were some 30 clocks of
the CPU's side of a phase.
"""

from types import SimpleNamespace

from migen import Module, Signal, Memory, Array, Cat, If, FSM, NextState, NextValue, Mux
from litex.soc.interconnect import wishbone
from litex.soc.interconnect.csr import AutoCSR, CSRStatus, CSRStorage

from deform_gateware.mvu import Mvu, LANES, SUM_BITS, HALF_SUM_BITS, bits_for, magnitude

# Where an SoC puts the region: uncached I/O on the VexRiscv (bit 31 set), below LiteX's CSRs.
REGION_ORIGIN = 0x9000_0000
REGION_SIZE = 0x100_0000
P_OFFSET = 0x00_0000
KP_OFFSET = 0x10_0000
OWNER_OFFSET = 0x30_0000
SHARED_OFFSET = 0x34_0000
UNIT_OFFSET = 0x80_0000
UNIT_STRIDE = 0x10_0000
UNIT_WORDS = 0x0_0000
UNIT_TILES = 0x8_0000
UNIT_LENGTH = 0xC_0000
MAX_UNITS = 8
P_KP_BITS = 128

# floor(x / 3) = (x * DIV3) >> DIV3_SHIFT for every x < 3 * 2^16 (the Kp window's i64 index).
DIV3 = 174763
DIV3_SHIFT = 19

CONSTANTS = dict(P_OFFSET=P_OFFSET, KP_OFFSET=KP_OFFSET, OWNER_OFFSET=OWNER_OFFSET,
                 SHARED_OFFSET=SHARED_OFFSET, UNIT_OFFSET=UNIT_OFFSET, UNIT_STRIDE=UNIT_STRIDE,
                 UNIT_WORDS=UNIT_WORDS, UNIT_TILES=UNIT_TILES, UNIT_LENGTH=UNIT_LENGTH)

# What a decoded bus address points at.
T_NONE, T_P, T_PAD, T_KP, T_OWNER, T_SHARED, T_WORD, T_TILE, T_LENGTH = range(9)


class Tables:
    """The array's own memories (a plain holder, invisible to LiteX's AutoCSR)."""

    def __init__(self, owner, shared, pad):
        self.owner, self.shared, self.pad = owner, shared, pad


class MvuArray(Module, AutoCSR):
    """``mvus`` MVUs (0 to 8), each with ``words`` words, ``tiles`` tiles, ``nodes`` rows."""

    def __init__(self, mvus, words=8192, tiles=256, nodes=1024, primitive=False):
        assert 0 <= mvus <= MAX_UNITS and nodes <= 1 << 16 and words <= 1 << 16
        self.mvus, self.words_depth, self.tiles_depth, self.nodes_depth = mvus, words, tiles, nodes
        self.bus = wishbone.Interface(data_width=32, adr_width=30)

        self.count = CSRStatus(4, reset=mvus, description="MVUs in the array")
        self.nodes = CSRStatus(32, reset=nodes, description="Rows of p and Kp (largest n)")
        self.words = CSRStatus(32, reset=words, description="Word entries per MVU")
        self.tiles = CSRStatus(32, reset=tiles, description="Tiles per MVU")
        self.n = CSRStorage(32, description="The matrix dimension n")
        self.directions = CSRStorage(2, reset=1, description="Fused directions, 1 to 3")
        self.shared_rows = CSRStorage(32, description="Entries of the shared-rows list")
        self.kp_plain = CSRStorage(1, reset=1,
            description="1: Kp rows live in MVU 0's memory (no program loaded)")
        self.start = CSRStorage(1, description="Write to run one MVU phase")
        self.busy = CSRStatus(1, description="A phase is running")
        self.phases = CSRStatus(32, description="Phases run since reset (wraps)")
        self.cycles = CSRStatus(32, description="Clocks of the phases since reset (wraps)")
        self.stalls = CSRStatus(32,
            description="Clocks MVU 0's fetch waited in the phases since reset (wraps)")
        self.p_kp = [CSRStatus(P_KP_BITS, name="p_kp%d" % d, description="pᵀKp, direction %d" % d)
                     for d in range(LANES)]
        self.kp_or = [CSRStatus(SUM_BITS, name="kp_or%d" % d,
                                description="OR of |Kp| (one's complement), direction %d" % d)
                      for d in range(LANES)]
        for d in range(LANES):
            setattr(self, "p_kp%d" % d, self.p_kp[d])
            setattr(self, "kp_or%d" % d, self.kp_or[d])

        self.units = [Mvu(words, tiles, nodes, primitive=primitive) for _ in range(mvus)]
        for k, unit in enumerate(self.units):
            setattr(self.submodules, "mvu%d" % k, unit)
        self.lengths = [Signal(bits_for(words + 1)) for _ in range(mvus)]
        for unit, length in zip(self.units, self.lengths):
            self.comb += [
                unit.length.eq(length),
                unit.last_row.eq(self.n.storage - 1),
                unit.directions.eq(self.directions.storage),
            ]

        # The row owners, the shared-rows list and p's padding lane. (Kept out of the module's
        # attributes: LiteX would map an AutoCSR module's memories onto the CSR bus.)
        table_depth = nodes if mvus else 2
        self.tables = Tables(Memory(3, table_depth, name="owner"),
                             Memory(32, table_depth, name="shared"),
                             Memory(32, table_depth, name="pad"))
        self.specials += self.tables.owner, self.tables.shared, self.tables.pad
        self.owner_rd = self.tables.owner.get_port()
        self.owner_wr = self.tables.owner.get_port(write_capable=True)
        self.shared_rd = self.tables.shared.get_port()
        self.shared_wr = self.tables.shared.get_port(write_capable=True)
        self.pad_rd = self.tables.pad.get_port()
        self.pad_wr = self.tables.pad.get_port(write_capable=True)
        self.specials += [self.owner_rd, self.owner_wr, self.shared_rd, self.shared_wr,
                          self.pad_rd, self.pad_wr]

        self.phase_busy = Signal()
        # The phase, state by state, built in the order its signals were always made in (see
        # the bus below for why the order matters).
        phase = SimpleNamespace()
        if self._phase(phase):
            self._phase_reduce(phase)
            self._phase_sum(phase)
        # The bus, step by step. The builders are called from here, one after another, in the
        # order the signals were always made in, and hand their signals on in `access`: Migen
        # names a signal after the variable that holds it and the `self` frames it was made in,
        # and orders its Verilog by when it was made, so a builder called from another builder,
        # or another order, would rename or reorder the Verilog.
        access = SimpleNamespace()
        self._bus_access(access)
        self._bus_decode(access)
        self._bus_read_addresses(access)
        self._bus_read(access)
        self._bus_write(access)

    # The phase -----------------------------------------------------------------------------------

    def _phase(self, ph):
        """The phase's registers and status, and its first two states: IDLE starts every MVU,
        RUN counts clocks until none is busy. Hands on in ``ph`` what the later states share;
        False with no MVUs, where there is no phase."""
        units = self.units
        n_units = len(units)
        self.reduce_row = Signal(bits_for(self.nodes_depth))
        self.reduce_owner = Signal(3)
        self.reduce_we = Signal()
        self.reduce_sum = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        self.reduce_entry = entry = Signal(bits_for(self.nodes_depth + 1))
        mask = Signal(8)
        m = Signal(4)
        total_or = [Signal(SUM_BITS) for _ in range(LANES)]
        total_low = [Signal((HALF_SUM_BITS + 4, True)) for _ in range(LANES)]
        total_high = [Signal((HALF_SUM_BITS + 4, True)) for _ in range(LANES)]
        cycles = Signal(32)
        phases = Signal(32)
        self.comb += [self.cycles.status.eq(cycles), self.phases.status.eq(phases),
                      self.busy.status.eq(self.phase_busy)]
        if n_units:
            self.comb += self.stalls.status.eq(units[0].stalls)

        if not n_units:
            return False
        fsm = FSM(reset_state="IDLE")
        self.submodules.phase = fsm
        self.comb += self.phase_busy.eq(~fsm.ongoing("IDLE"))
        any_busy = Signal()
        self.comb += any_busy.eq(Cat(*[u.busy for u in units]) != 0)
        fsm.act("IDLE",
            If(self.start.re,
                *[u.start.eq(1) for u in units],
                NextValue(phases, phases + 1),
                *[NextValue(o, 0) for o in total_or],
                NextState("RUN")))
        fsm.act("RUN",
            NextValue(cycles, cycles + 1),
            If(~any_busy, NextValue(entry, 0), NextState("REDUCE")))
        ph.__dict__.update(fsm=fsm, entry=entry, mask=mask, m=m, cycles=cycles,
                           total_or=total_or, total_low=total_low, total_high=total_high)
        return True

    def _phase_reduce(self, ph):
        """REDUCE to REDUCE_WRITE: each shared row's Kp summed over the MVUs in its mask, one
        MVU per clock, into its owner, and ORed into max |Kp|."""
        units, fsm, entry, mask, m, cycles = (self.units, ph.fsm, ph.entry, ph.mask, ph.m,
                                              ph.cycles)
        n_units, total_or, totals = len(units), ph.total_or, ph.total_low + ph.total_high
        # The shared rows: read the list entry, then every MVU's Kp at its row, one MVU per
        # clock into the sum (those in the mask), then the sum into the owner.
        fsm.act("REDUCE",
            NextValue(cycles, cycles + 1),
            If(entry == self.shared_rows.storage,
                NextValue(m, 0),
                *[NextValue(t, 0) for t in totals],
                NextState("SUM"),
            ).Else(NextState("REDUCE_ROW")))
        fsm.act("REDUCE_ROW",
            NextValue(cycles, cycles + 1),
            NextValue(self.reduce_row, self.shared_rd.dat_r[0:16]),
            NextValue(mask, self.shared_rd.dat_r[16:24]),
            NextValue(self.reduce_owner, self.shared_rd.dat_r[24:27]),
            *[NextValue(s, 0) for s in self.reduce_sum],
            NextValue(m, 0),
            NextState("REDUCE_WAIT"))
        # Kp read addresses are presented from REDUCE_WAIT on (reduce_row is registered); the
        # block RAMs answer LATENCY clocks later.
        fsm.act("REDUCE_WAIT", NextValue(cycles, cycles + 1), NextState("REDUCE_WAIT2"))
        fsm.act("REDUCE_WAIT2", NextValue(cycles, cycles + 1), NextState("REDUCE_ADD"))
        chosen = [Signal((SUM_BITS, True)) for _ in range(LANES)]
        chosen_entry = Signal(LANES * SUM_BITS)
        self.comb += chosen_entry.eq(Array([u.bus_kp.dat_r for u in units])[m])
        self.comb += [c.eq(chosen_entry[SUM_BITS * i:SUM_BITS * (i + 1)])
                      for i, c in enumerate(chosen)]
        fsm.act("REDUCE_ADD",
            NextValue(cycles, cycles + 1),
            If((mask >> m)[0],
                *[NextValue(s, s + c) for s, c in zip(self.reduce_sum, chosen)]),
            NextValue(m, m + 1),
            If(m == n_units - 1, NextState("REDUCE_WRITE")))
        fsm.act("REDUCE_WRITE",
            NextValue(cycles, cycles + 1),
            self.reduce_we.eq(1),
            *[NextValue(o, o | magnitude(s)) for o, s in zip(total_or, self.reduce_sum)],
            NextValue(entry, entry + 1),
            NextState("REDUCE"))

    def _phase_sum(self, ph):
        """SUM and JOIN: the MVUs' Σ p·low, Σ p·high and ORs summed, one MVU per clock, into
        ``p_kp*`` and ``kp_or*``."""
        units, fsm, m, cycles = self.units, ph.fsm, ph.m, ph.cycles
        n_units, total_or, total_low, total_high = (len(units), ph.total_or, ph.total_low,
                                                    ph.total_high)
        # Σ over the MVUs, one per clock.
        fsm.act("SUM",
            NextValue(cycles, cycles + 1),
            *[NextValue(t, t + Array([u.p_kp_low[d] for u in units])[m])
              for d, t in enumerate(total_low)],
            *[NextValue(t, t + Array([u.p_kp_high[d] for u in units])[m])
              for d, t in enumerate(total_high)],
            *[NextValue(o, o | Array([u.kp_or[d] for u in units])[m])
              for d, o in enumerate(total_or)],
            NextValue(m, m + 1),
            If(m == n_units - 1, NextState("JOIN")))
        # pᵀKp = Σ p·low + 2^32 · Σ p·high.
        joined = [Signal((P_KP_BITS, True)) for _ in range(LANES)]
        self.comb += [j.eq(lo + (hi << 32)) for j, lo, hi in zip(joined, total_low, total_high)]
        fsm.act("JOIN",
            NextValue(cycles, cycles + 1),
            *[NextValue(s.status, j) for s, j in zip(self.p_kp, joined)],
            *[NextValue(s.status, o) for s, o in zip(self.kp_or, total_or)],
            NextState("IDLE"))

    # The bus -------------------------------------------------------------------------------------

    def _bus_access(self, access):
        """IDLE: a Wishbone access, taken only while no phase runs, latched whole (word
        offset in the region, data, byte enables, write) for the steps that decode it; and
        the registers the decode fills (``target``, ``index``, ``sub``, ``unit``, ``i64``)."""
        bus = self.bus
        word_offset = Signal(22)
        data = Signal(32)
        sel = Signal(4)
        we = Signal()
        target = Signal(4)
        index = Signal(17)
        sub = Signal(3)
        unit = Signal(3)
        i64 = Signal(19)
        in_unit = Signal(18)
        self.comb += in_unit.eq(word_offset - UNIT_OFFSET // 4 - unit * (UNIT_STRIDE // 4))
        latch = Signal()

        fsm = FSM(reset_state="IDLE")
        self.submodules.slave = fsm
        fsm.act("IDLE",
            If(bus.cyc & bus.stb & ~self.phase_busy,
                NextValue(word_offset, bus.adr[0:22]),
                NextValue(data, bus.dat_w), NextValue(sel, bus.sel), NextValue(we, bus.we),
                NextState("DECODE")))
        access.word_offset, access.data, access.sel, access.we = word_offset, data, sel, we
        access.target, access.index, access.sub, access.unit = target, index, sub, unit
        access.i64, access.in_unit, access.latch, access.fsm = i64, in_unit, latch, fsm

    def _bus_decode(self, access):
        """DECODE and UNIT: which memory the word offset points at, which entry and which
        32-bit part of it (a Kp entry's index by a multiplication for the division by 3, the
        lane and half a clock later; an MVU's word, tile or length in UNIT); then READ, WAIT
        and LATCH while the block RAMs answer."""
        units, fsm, word_offset = self.units, access.fsm, access.word_offset
        target, index, sub, unit = access.target, access.index, access.sub, access.unit
        i64, in_unit, latch = access.i64, access.in_unit, access.latch

        def region(offset, size):
            lo = offset // 4
            return (word_offset >= lo) & (word_offset < lo + size // 4)

        # Which memory, which entry, which part of the entry.
        kp_index = Signal(19)
        # The product in a signal of its own width: in Verilog `a * b >> s` assigned to a narrow
        # target is evaluated at the target's width (Migen's simulator would not notice).
        kp_product = Signal(len(kp_index) + DIV3.bit_length())
        self.comb += [kp_index.eq((word_offset - KP_OFFSET // 4) >> 1),
                      kp_product.eq(kp_index * DIV3)]
        fsm.act("DECODE",
            NextValue(target, T_NONE), NextValue(sub, 0),
            NextValue(unit, (word_offset - UNIT_OFFSET // 4) >> 18),
            If(region(P_OFFSET, KP_OFFSET - P_OFFSET),
                NextValue(target, Mux(word_offset[0:2] == 3, T_PAD, T_P)),
                NextValue(index, word_offset >> 2),
                NextValue(sub, Mux(word_offset[0:2] == 3, 0, word_offset[0:2])),
            ).Elif(region(KP_OFFSET, OWNER_OFFSET - KP_OFFSET),
                NextValue(target, T_KP),
                NextValue(i64, kp_index),
                NextValue(index, kp_product[DIV3_SHIFT:]),
                NextValue(sub, word_offset[0]),
            ).Elif(region(OWNER_OFFSET, SHARED_OFFSET - OWNER_OFFSET),
                NextValue(target, T_OWNER), NextValue(index, word_offset - OWNER_OFFSET // 4),
            ).Elif(region(SHARED_OFFSET, UNIT_OFFSET - SHARED_OFFSET),
                NextValue(target, T_SHARED), NextValue(index, word_offset - SHARED_OFFSET // 4),
            ),
            NextState("UNIT"))
        # The i64's lane (0..2) and half make the sub-word of a Kp entry (0..5); an MVU's region.
        fsm.act("UNIT",
            If(target == T_KP,
                NextValue(sub, Cat(sub[0], (i64 - index * 3)[0:2])),
            ).Elif(word_offset >= UNIT_OFFSET // 4,
                If(unit < len(units),
                    If(in_unit < (UNIT_TILES - UNIT_WORDS) // 4,
                        NextValue(target, T_WORD), NextValue(index, in_unit >> 1),
                    ).Elif(in_unit < (UNIT_LENGTH - UNIT_WORDS) // 4,
                        NextValue(target, T_TILE),
                        NextValue(index, (in_unit - UNIT_TILES // 4) >> 1),
                    ).Elif(in_unit == (UNIT_LENGTH - UNIT_WORDS) // 4,
                        NextValue(target, T_LENGTH)),
                    NextValue(sub, in_unit[0]))),
            NextState("READ"))
        # The block RAMs answer LATENCY (2) clocks after the address: p's, Kp's and the tables'
        # address is set in DECODE, so their entry is latched at the end of WAIT; an MVU's word
        # or tile address is set in UNIT, a clock later, so those entries wait a clock more
        # (LATCH; they are only ever loaded, never touched per iteration).
        fsm.act("READ", NextState("WAIT"))
        fsm.act("WAIT", latch.eq(1),
            If((target == T_WORD) | (target == T_TILE), NextState("LATCH")).Else(
                NextState("DATA")))
        fsm.act("LATCH", latch.eq(1), NextState("DATA"))

    def _bus_read_addresses(self, access):
        """Every memory's bus address, the decoded index; Kp's and the shared list's are the
        reduction's while a phase runs."""
        units, index = self.units, access.index
        # Read addresses, from the decoded index (the phase's own while it runs).
        for u in units:
            self.comb += [
                u.bus_p.adr.eq(index), u.bus_word.adr.eq(index), u.bus_tile.adr.eq(index),
                If(self.phase_busy, u.bus_kp.adr.eq(self.reduce_row)).Else(
                    u.bus_kp.adr.eq(index)),
            ]
        self.comb += [
            self.owner_rd.adr.eq(index), self.owner_wr.adr.eq(index),
            self.shared_wr.adr.eq(index),
            self.pad_rd.adr.eq(index), self.pad_wr.adr.eq(index),
        ]
        # The shared list's read port is the reduction's while a phase runs.
        self.comb += self.shared_rd.adr.eq(
            Mux(self.phase_busy, self.reduce_entry, index) if units else index)

    def _bus_read(self, access):
        """The addressed entry latched (``entry``: every path from a block RAM to the bus or
        another memory goes through this register), the 32-bit word the bus reads, and the
        entry as a write would leave it (``entry_new``: the word merged by byte enables)."""
        units, target, unit, latch = self.units, access.target, access.unit, access.latch
        sub, sel, data = access.sub, access.sel, access.data
        # The entry as read, latched (`entry`), and the word the bus reads. Every path from a
        # block RAM's output to the bus or to another memory's input goes through a register:
        # combinational, the read-modify-write from one MVU's block RAM through the multiplexers
        # into the other MVUs' inputs across the device was the 2-MVU SoC's critical path
        # (24.9 ns of which 17 of wire, 40.1 MHz against 46.8 without MVUs).
        owner = Signal(3)
        self.sync += owner.eq(Mux(self.kp_plain.storage, 0, self.owner_rd.dat_r))
        nothing = Signal(LANES * SUM_BITS)
        kp_entries = Array([u.bus_kp.dat_r for u in units] or [nothing])
        read = Signal(LANES * SUM_BITS)
        entry = Signal(LANES * SUM_BITS)
        word = Signal(32)
        merged = Signal(32)
        cases = {
            T_P: units[0].bus_p.dat_r if units else 0,
            T_PAD: self.pad_rd.dat_r,
            T_KP: kp_entries[owner] if units else 0,
            T_OWNER: self.owner_rd.dat_r,
            T_SHARED: self.shared_rd.dat_r,
            T_WORD: Array([u.bus_word.dat_r for u in units] or [nothing])[unit],
            T_LENGTH: Array(self.lengths or [nothing])[unit],
        }
        self.comb += [If(target == t, read.eq(v)) for t, v in cases.items()]
        self.sync += If(latch, entry.eq(read))
        self.comb += word.eq(Array([entry[32 * i:32 * (i + 1)] for i in range(6)])[sub])
        self.comb += merged.eq(Cat(*[Mux(sel[i], data[8 * i:8 * (i + 1)], word[8 * i:8 * (i + 1)])
                                     for i in range(4)]))
        entry_new = Signal(LANES * SUM_BITS)
        self.comb += entry_new.eq(entry)
        self.comb += Array([entry_new[32 * i:32 * (i + 1)] for i in range(6)])[sub].eq(merged)
        access.owner, access.word, access.merged, access.entry_new = owner, word, merged, entry_new

    def _bus_write(self, access):
        """DATA: the bus acknowledged; a write lands a clock later from registers, in the
        addressed memory (p in every MVU, Kp in its owner, an MVU's word, tile or length),
        while the next access is still in IDLE."""
        bus, units, fsm = self.bus, self.units, access.fsm
        target, unit, sub, we = access.target, access.unit, access.sub, access.we
        owner, word, merged, entry_new = access.owner, access.word, access.merged, access.entry_new
        # A write lands a clock after DATA, from registers (`written`, `new_entry`, `merged_r`), in
        # the next access's IDLE: its target, unit, sub-word and owner change only in that
        # access's DECODE and UNIT, and its first read address two clocks later still.
        write = Signal()
        written = Signal()
        new_entry = Signal(LANES * SUM_BITS)
        merged_r = Signal(32)
        self.sync += [written.eq(write), new_entry.eq(entry_new), merged_r.eq(merged)]
        # A tile entry's first word waits here for its second.
        tile_low = Signal(32)
        self.sync += If(write & (target == T_TILE) & (sub == 0), tile_low.eq(merged))
        fsm.act("DATA",
            bus.ack.eq(1), bus.dat_r.eq(word),
            write.eq(we),
            NextState("IDLE"))
        for k, u in enumerate(units):
            is_owner = owner == k
            self.comb += [
                u.bus_p.dat_w.eq(new_entry), u.bus_p.we.eq(written & (target == T_P)),
                u.bus_word.dat_w.eq(new_entry), u.bus_word.we.eq(written & (target == T_WORD)
                                                                 & (unit == k)),
                u.bus_tile.dat_w.eq(self._tile_from_bus(u, tile_low, merged_r)),
                u.bus_tile.we.eq(written & (target == T_TILE) & (unit == k) & (sub == 1)),
                If(self.phase_busy,
                    u.bus_kp.dat_w.eq(Cat(*self.reduce_sum)),
                    u.bus_kp.we.eq(self.reduce_we & (self.reduce_owner == k)),
                ).Else(
                    u.bus_kp.dat_w.eq(new_entry),
                    u.bus_kp.we.eq(written & (target == T_KP) & is_owner)),
            ]
            self.sync += If(written & (target == T_LENGTH) & (unit == k),
                            self.lengths[k].eq(merged_r))
        self.comb += [
            self.owner_wr.dat_w.eq(merged_r), self.owner_wr.we.eq(written & (target == T_OWNER)),
            self.shared_wr.dat_w.eq(merged_r), self.shared_wr.we.eq(written & (target == T_SHARED)),
            self.pad_wr.dat_w.eq(merged_r), self.pad_wr.we.eq(written & (target == T_PAD)),
        ]

    def _tile_from_bus(self, u, low, high):
        """A tile-table entry from its two bus words (see the module's documentation)."""
        nb = u.node_bits
        return Cat(low[0:nb], low[16:16 + nb], high[0:nb], high[31])


def add_to_soc(soc, mvus, words, tiles, nodes, primitive=False):
    """Adds an MVU array to a LiteX SoC: its registers (``mvus_*``), its region (``mvus``) and
    the layout constants (``MVUS_*``) the firmware's build reads from csr.json. ``primitive``:
    ECP5 block RAM primitives with their output registers (a board's bitstream; see ``bram``)."""
    from litex.soc.integration.soc import SoCRegion
    soc.mvus = MvuArray(mvus, words=words, tiles=tiles, nodes=nodes, primitive=primitive)
    soc.bus.add_slave("mvus", soc.mvus.bus,
                      SoCRegion(origin=REGION_ORIGIN, size=REGION_SIZE, cached=False))
    for name, value in CONSTANTS.items():
        soc.add_constant("MVUS_" + name, value)
