"""Block RAM with registered outputs: one write port and one or two read ports, each read
answering ``LATENCY`` = 2 clocks after its address (the address is registered, and so is the
data).

Why not a plain Migen ``Memory``: Yosys maps a memory onto ECP5 block RAM (DP16KD) without the
block's own output register, so its data leaves the block ~5.8 ns after the clock at speed grade
-6 and nothing more than a register fits behind it at 133 MHz (a block read feeding an adder
measured 93 MHz; with the output register on, 263 MHz). So:

- ``primitive=False`` (simulation, Verilator, any FPGA): a Migen ``Memory`` and a register behind
  each read port: the same latency, for any synthesis tool to map as it likes.
- ``primitive=True`` (ECP5): DP16KD blocks instantiated with ``REGMODE_*="OUTREG"``, one column
  of blocks per ``w`` bits of the word, ``w`` = 18, 9, 4, 2 or 1 as the depth allows (1024 to
  16384 rows), never blocks stacked in depth (that would put a multiplexer behind the blocks).
  The ports are wired as Yosys's own DP16KD mapping wires them (``brams_map_16kd.v``: the address
  in the top bits of the 14-bit bus, an 18-bit write's byte enables in its two low bits).

With two read ports, read port 0 and the write port share the block's port A: the caller never
reads through port 0 in a clock in which it writes (the MVU reads p only while running and the
bus writes it only while the MVU is idle).

A memory of at most ``PDP_ROWS`` (512) rows with one read port uses the block's 36-bit
pseudo-dual-port mode instead (Lattice's PDPW16KD: 512 x 36, port A writes, port B reads), wired
as Yosys's own map of that mode wires a DP16KD (``brams_map_16kd.v``, ``$__PDPW16KD_``): both
data widths 36, the row in the top 9 address bits, the write's four byte enables in ADA[3:0],
the word's low 18 bits on the A pins and its high 18 on the B pins, in and out. Its read answers
as the true-dual-port columns' do (the write on port A, the read on port B), in half the blocks:
a 192-bit memory in 6 blocks, not 11. At more than 512 rows that mode saves nothing (a block
holds 18 kbit either way), and a second read port needs the true-dual-port columns.
"""

from migen import Module, Signal, Memory, Instance, ClockSignal, If, Replicate

LATENCY = 2
# The 36-bit pseudo-dual-port mode: its width and rows.
PDP_WIDTH, PDP_ROWS = 36, 512


class ReadPort:
    def __init__(self, adr_bits, width):
        self.adr = Signal(adr_bits)
        self.dat = Signal(width)


def depth_bits(depth):
    return max(1, (depth - 1).bit_length())


def block_width(depth):
    """The widest DP16KD data width (at most 18) that holds ``depth`` rows in one block."""
    for width, rows in ((18, 1024), (9, 2048), (4, 4096), (2, 8192), (1, 16384)):
        if depth <= rows:
            return width, rows
    raise ValueError("a block RAM of more than 16384 rows would need stacked blocks")


class Bram(Module):
    """``width`` x ``depth`` bits; ``self.adr/dat_w/we`` the write port, ``self.read[k]`` the
    read ports; ``self.memory`` the Migen Memory when not a primitive (for testbenches)."""

    def __init__(self, width, depth, read_ports=1, primitive=False):
        assert read_ports in (1, 2)
        self.width, self.depth = width, depth
        bits = depth_bits(depth)
        self.adr = Signal(bits)
        self.dat_w = Signal(width)
        self.we = Signal()
        self.read = [ReadPort(bits, width) for _ in range(read_ports)]
        self.memory = None
        if primitive and read_ports == 1 and depth <= PDP_ROWS:
            self._pdp_blocks(width)
        elif primitive:
            self._blocks(width, depth)
        else:
            self._generic(width, depth)

    def _generic(self, width, depth):
        self.specials.memory = memory = Memory(width, depth)
        write = memory.get_port(write_capable=True)
        self.specials += write
        self.comb += [write.adr.eq(self.adr), write.dat_w.eq(self.dat_w), write.we.eq(self.we)]
        for port in self.read:
            read = memory.get_port()
            self.specials += read
            self.comb += read.adr.eq(port.adr)
            self.sync += port.dat.eq(read.dat_r)

    def _blocks(self, width, depth):
        w, rows = block_width(depth)
        shift = 14 - depth_bits(rows)          # the row address sits in the top bits
        two = len(self.read) == 2
        # Port A: the write address while writing, else read port 0's.
        adr_a = Signal(len(self.adr))
        if two:
            self.comb += If(self.we, adr_a.eq(self.adr)).Else(adr_a.eq(self.read[0].adr))
        else:
            self.comb += adr_a.eq(self.adr)
        a_adr = Signal(14)
        b_adr = Signal(14)
        low = Replicate(self.we, 2) if w == 18 else 0   # an 18-bit write's byte enables
        self.comb += [a_adr.eq((adr_a << shift) | low), b_adr.eq(self.read[-1].adr << shift)]
        for b in range((width + w - 1) // w):
            lo, hi = b * w, min(width, (b + 1) * w)
            di = Signal(18)
            do_a = Signal(18)
            do_b = Signal(18)
            self.comb += di.eq(self.dat_w[lo:hi])
            if two:
                self.comb += self.read[0].dat[lo:hi].eq(do_a)
            self.comb += self.read[-1].dat[lo:hi].eq(do_b)
            ports = self._block_ports(w, "OUTREG" if two else "NOREG", a_adr, b_adr)
            ports.update(p_WRITEMODE_A="NORMAL", p_WRITEMODE_B="NORMAL")
            for k in range(18):
                ports["i_DIA%d" % k] = di[k]
                ports["i_DIB%d" % k] = 0
                ports["o_DOA%d" % k] = do_a[k]
                ports["o_DOB%d" % k] = do_b[k]
            self.specials += Instance("DP16KD", **ports)

    def _block_ports(self, width, regmode_a, a_adr, b_adr):
        """A DP16KD's ports common to both modes: ``width`` bits a port, port B's output
        registered (and port A's as ``regmode_a``), both clocked every cycle, never reset or
        chip-selected, port A writing when ``we``, and the two 14-bit addresses."""
        ports = dict(
            p_DATA_WIDTH_A=width, p_DATA_WIDTH_B=width,
            p_REGMODE_A=regmode_a, p_REGMODE_B="OUTREG",
            p_RESETMODE="SYNC", p_CSDECODE_A="0b000", p_CSDECODE_B="0b000",
            i_CLKA=ClockSignal(), i_CLKB=ClockSignal(),
            i_CEA=1, i_CEB=1, i_OCEA=1, i_OCEB=1, i_RSTA=0, i_RSTB=0,
            i_WEA=self.we, i_WEB=0,
        )
        for k in range(3):
            ports["i_CSA%d" % k] = 0
            ports["i_CSB%d" % k] = 0
        for k in range(14):
            ports["i_ADA%d" % k] = a_adr[k]
            ports["i_ADB%d" % k] = b_adr[k]
        return ports

    def _pdp_blocks(self, width):
        shift = 14 - depth_bits(PDP_ROWS)      # the row in ADx[13:5]
        half = PDP_WIDTH // 2
        a_adr = Signal(14)
        b_adr = Signal(14)
        # ADA[3:0]: the four 9-bit byte enables of the 36-bit write; ADA4 and ADB[4:0] unused.
        self.comb += [a_adr.eq((self.adr << shift) | Replicate(self.we, 4)),
                      b_adr.eq(self.read[0].adr << shift)]
        for b in range((width + PDP_WIDTH - 1) // PDP_WIDTH):
            lo, hi = b * PDP_WIDTH, min(width, (b + 1) * PDP_WIDTH)
            di = Signal(PDP_WIDTH)
            do = Signal(PDP_WIDTH)
            self.comb += [di.eq(self.dat_w[lo:hi]), self.read[0].dat[lo:hi].eq(do)]
            ports = self._block_ports(PDP_WIDTH, "OUTREG", a_adr, b_adr)
            for k in range(half):
                ports["i_DIA%d" % k] = di[k]
                ports["i_DIB%d" % k] = di[half + k]
                ports["o_DOA%d" % k] = do[k]
                ports["o_DOB%d" % k] = do[half + k]
            self.specials += Instance("DP16KD", **ports)
