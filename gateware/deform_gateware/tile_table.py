"""An MVU's tile table: per tile ``row_base``, ``col_base``, ``n - 1 - col_base`` and the mirrored
bit (``target-core/src/mvu_program.rs``), read in tile order, one tile further per ``shift``.

A phase reads the table strictly in order, so the table need not answer an arbitrary address in
the same clock: it shows the header of the tile at its cursor (``dat``) from registers. Its
entries are split into two banks of distributed RAM, even tiles and odd tiles; each bank is read
every clock at its own cursor (the even and the odd one of the two tiles from the cursor on),
into a register; ``dat`` is the one of the two registers the cursor's parity picks. A ``shift``
moves the cursor by one, possibly every clock: the tile it moves to was the other of the pair,
already read. So the table's read (a bank's 128 entries: its address fanned out to 64 RAM cells
and an 8-way multiplexer) ends in a register beside the banks, and what the MVU loads from
``dat`` is a 2-way select of registers. (One 256-entry table read in the same clock, its 16-way
multiplexer ending in the MVU's header register, was a critical path of the unit at 133 MHz.)

The banks are distributed RAM on purpose (``ram_style``): Yosys would otherwise map a bank with
its registered read onto a DP16KD, whose slow output without its own register would be the path.

Writes (from the MVU array's bus, while the unit is idle) must come at least a clock before the
phase's first read; ``rewind`` holds the cursor at tile 0 (while idle).
"""

from migen import Module, Signal, Memory, Mux, If


def _bits(n):
    return max(1, (n - 1).bit_length())


class TileTable(Module):
    """``depth`` entries of ``width`` bits; ``dat`` is the entry at the cursor."""

    def __init__(self, width, depth):
        self.depth = depth
        # The array's write port.
        self.adr = Signal(_bits(depth))
        self.dat_w = Signal(width)
        self.we = Signal()
        # The phase's side.
        self.rewind = Signal()
        self.shift = Signal()
        self.dat = Signal(width)

        half = max(2, (depth + 1) // 2)
        self.banks = [Memory(width, half, name="tile_bank%d" % b) for b in range(2)]
        cursors = [Signal(_bits(half)) for _ in range(2)]   # each bank's of the pair
        odd = Signal()                                      # the cursor's tile is odd
        read = [Signal(width) for _ in range(2)]
        for b, bank in enumerate(self.banks):
            bank.attr = {("ram_style", "distributed")}
            rd = bank.get_port(async_read=True)
            wr = bank.get_port(write_capable=True)
            self.specials += bank, rd, wr
            self.comb += [
                rd.adr.eq(cursors[b]),
                wr.adr.eq(self.adr[1:]), wr.dat_w.eq(self.dat_w),
                wr.we.eq(self.we & (self.adr[0] == b)),
            ]
            self.sync += read[b].eq(rd.dat_r)
        self.comb += self.dat.eq(Mux(odd, read[1], read[0]))
        # A shift consumes the cursor's tile: its bank moves on to its next entry (the tile two
        # further), and the other bank's (the next tile) becomes the cursor's.
        self.sync += If(self.rewind,
            cursors[0].eq(0), cursors[1].eq(0), odd.eq(0),
        ).Elif(self.shift,
            odd.eq(~odd),
            If(odd, cursors[1].eq(cursors[1] + 1)).Else(cursors[0].eq(cursors[0] + 1)))

    def init(self, entries):
        """Simulation: the table's contents before the simulation starts."""
        entries = list(entries)
        entries += [0] * (2 * self.banks[0].depth - len(entries))
        for b, bank in enumerate(self.banks):
            bank.init = entries[b::2]
