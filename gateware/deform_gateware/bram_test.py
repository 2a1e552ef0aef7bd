"""The ECP5 block-RAM wiring (``Bram(primitive=True)``) against the generic memory: Migen cannot
simulate a DP16KD, so each instance is replaced by a model of the block as Lattice documents it
(TN1264; Yosys's ``brams_map_16kd.v`` wires it the same way) and both memories are driven with
the same random writes and reads, every read compared. The model checks the wiring (the
row's address bits for the data width, the byte enables, which data pins carry which bits, the
clock enables and chip selects, the output register); it cannot check the model against the
silicon — that is what a bitstream on the board does."""

import random
import unittest

from migen import Module, Signal, Memory, Cat

from deform_gateware.simulation import run_simulation
from migen.fhdl.specials import Instance

from deform_gateware.bram import Bram, LATENCY

# Rows of one block at each data width (a 36-bit word is the pseudo-dual-port mode).
ROWS = {36: 512, 18: 1024, 9: 2048, 4: 4096, 2: 8192, 1: 16384}


def _constant(expr, what):
    value = getattr(expr, "value", None)
    if value is None:
        raise AssertionError("%s is not a constant" % what)
    return value


class Dp16kdModel(Module):
    """One DP16KD: both ports of one width, registered reads (plus the output register with
    ``REGMODE_*="OUTREG"``). x36: port A writes ``{DIB, DIA}`` at ``ADA[13:5]`` with byte
    enables ``ADA[3:0]``, port B reads ``{DOB, DOA}`` at ``ADB[13:5]``. x18: the row in
    ``AD[13:4]``, the byte enables of a write in ``AD[1:0]``. x9, x4, ...: the row in the top
    bits."""

    def __init__(self, instance):
        params, ins, outs = {}, {}, {}
        for item in instance.items:
            if isinstance(item, Instance.Parameter):
                params[item.name] = getattr(item.value, "value", item.value)
            elif isinstance(item, Instance.Input):
                ins[item.name] = item.expr
            else:
                outs[item.name] = item.expr
        self.width = width = params["DATA_WIDTH_A"]
        assert params["DATA_WIDTH_B"] == width, "both ports of one width"
        rows = ROWS[width]
        shift = 14 - (rows - 1).bit_length()
        for name in ("CEA", "CEB", "OCEA", "OCEB"):
            assert _constant(ins[name], name) == 1, name
        for name in ("RSTA", "RSTB") + tuple("CS%s%d" % (p, k) for p in "AB" for k in range(3)):
            assert _constant(ins[name], name) == 0, name
        assert params["CSDECODE_A"] == params["CSDECODE_B"] == "0b000"

        def bus(prefix, n):
            return Cat(*[ins["%s%d" % (prefix, k)] for k in range(n)])

        def pins(prefix):
            return Cat(*[outs["%s%d" % (prefix, k)] for k in range(18)])

        def out_register(port, dat, regmode):
            if regmode == "OUTREG":
                self.sync += dat.eq(port.dat_r)
            else:
                assert regmode == "NOREG"
                self.comb += dat.eq(port.dat_r)

        ada, adb = bus("ADA", 14), bus("ADB", 14)
        if width == 36:
            assert _constant(ins["WEB"], "WEB") == 0, "x36: port B only reads"
            self.specials.memory = memory = Memory(36, rows)
            write = memory.get_port(write_capable=True, we_granularity=9)
            read = memory.get_port()
            self.specials += write, read
            self.comb += [
                write.adr.eq(ada[shift:]), write.dat_w.eq(Cat(bus("DIA", 18), bus("DIB", 18))),
                write.we.eq(Cat(*[ins["WEA"] & ada[k] for k in range(4)])),
                read.adr.eq(adb[shift:]),
            ]
            dat = Signal(36)
            out_register(read, dat, params["REGMODE_B"])
            self.comb += Cat(pins("DOA"), pins("DOB")).eq(dat)
            return
        self.specials.memory = memory = Memory(width, rows)
        for p, ad in (("A", ada), ("B", adb)):
            write = memory.get_port(write_capable=True, we_granularity=9 if width == 18 else 0)
            read = memory.get_port()
            self.specials += write, read
            we = ins["WE" + p]
            enables = Cat(*[we & ad[k] for k in range(2)]) if width == 18 else we
            self.comb += [write.adr.eq(ad[shift:]), write.dat_w.eq(bus("DI" + p, width)),
                          write.we.eq(enables), read.adr.eq(ad[shift:])]
            dat = Signal(width)
            out_register(read, dat, params["REGMODE_" + p])
            self.comb += pins("DO" + p)[:width].eq(dat)


def modelled(bram):
    """``bram`` with each DP16KD instance replaced by a ``Dp16kdModel``; the instances' count
    and data widths."""
    specials = bram._fragment.specials
    blocks = [s for s in specials if isinstance(s, Instance)]
    widths = []
    for instance in blocks:
        assert instance.of == "DP16KD"
        specials.remove(instance)
        model = Dp16kdModel(instance)
        bram.submodules += model
        widths.append(model.width)
    return len(blocks), sorted(set(widths))


class Pair(Module):
    def __init__(self, width, depth, read_ports):
        self.submodules.generic = Bram(width, depth, read_ports)
        self.submodules.block = Bram(width, depth, read_ports, primitive=True)
        self.blocks, self.widths = modelled(self.block)
        self.adr = Signal(len(self.generic.adr))
        self.dat_w = Signal(width)
        self.we = Signal()
        self.read_adr = [Signal(len(self.generic.adr)) for _ in range(read_ports)]
        for m in (self.generic, self.block):
            self.comb += [m.adr.eq(self.adr), m.dat_w.eq(self.dat_w), m.we.eq(self.we)]
            for port, adr in zip(m.read, self.read_adr):
                self.comb += port.adr.eq(adr)


def compare(test, width, depth, read_ports, clocks=600, seed=1):
    """Random writes and reads on both memories; returns how many reads were compared and how
    many of them were not zero."""
    rng = random.Random(seed)
    dut = Pair(width, depth, read_ports)
    counts = dict(compared=0, nonzero=0)

    # A few rows across the whole depth (the first and last among them), so that most reads
    # find a row written before: every address bit is exercised, and the data compared is not
    # an empty memory's.
    rows = sorted(set([0, depth - 1] + [rng.randrange(depth) for _ in range(min(depth, 30))]))

    def bench():
        history = []          # per clock: which ports' reads are meaningful
        for t in range(clocks):
            we = rng.random() < 0.4
            adr = rng.choice(rows)
            yield dut.we.eq(we)
            yield dut.adr.eq(adr)
            yield dut.dat_w.eq(rng.getrandbits(width))
            valid = []
            for k, port in enumerate(dut.read_adr):
                r = rng.choice(rows)
                # Port 0 of a two-port memory shares the block's port A with the write: the
                # caller never reads it while writing. A read of the row written in the same
                # clock is a collision neither memory defines.
                valid.append(not (we and read_ports == 2 and k == 0) and not (we and r == adr))
                yield port.eq(r)
            history.append(valid)
            yield
            if t >= LATENCY:
                for k in range(read_ports):
                    if not history[t - LATENCY][k]:
                        continue
                    got = yield dut.block.read[k].dat
                    want = yield dut.generic.read[k].dat
                    test.assertEqual(got, want, "%d x %d, port %d, clock %d"
                                     % (width, depth, k, t))
                    counts["compared"] += 1
                    counts["nonzero"] += want != 0

    run_simulation(dut, bench())
    return dut, counts


class PrimitiveWiringTest(unittest.TestCase):
    def check(self, width, depth, read_ports, blocks, widths):
        dut, counts = compare(self, width, depth, read_ports)
        self.assertEqual((dut.blocks, dut.widths), (blocks, widths))
        # Enough reads of written rows, so the comparison is not of empty memories.
        self.assertGreater(counts["nonzero"], counts["compared"] // 4, counts)

    def test_kp_at_512_rows_in_the_36_bit_mode(self):
        self.check(192, 512, 1, 6, [36])

    def test_p_row_at_512_rows_in_the_36_bit_mode(self):
        self.check(96, 512, 1, 3, [36])

    def test_a_small_memory_in_the_36_bit_mode(self):
        self.check(40, 16, 1, 2, [36])

    def test_p_col_at_512_rows_keeps_two_read_ports_on_18_bit_columns(self):
        self.check(96, 512, 2, 6, [18])

    def test_kp_at_1024_rows_on_18_bit_columns(self):
        self.check(192, 1024, 1, 11, [18])

    def test_p_col_at_1024_rows(self):
        self.check(96, 1024, 2, 6, [18])

    def test_the_words_at_4096_rows_on_4_bit_columns(self):
        self.check(36, 4096, 1, 9, [4])


if __name__ == "__main__":
    unittest.main()
