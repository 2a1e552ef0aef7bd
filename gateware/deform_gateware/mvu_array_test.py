"""The MVU array in Migen's simulator against the portable kernel's vectors: every case (1 to 3
MVUs, rows and overlap splits with their shared rows, mirroring, 1 to 3 directions, matrices
wider than a column window, rows at the edge of exact sums), two phases where the case has
them; and one case loaded and read entirely through the array's bus, as the firmware does it."""

import sys
import time
import unittest

from deform_gateware.simulation import run_simulation

from deform_gateware import testvectors
from deform_gateware.mvu_array import (MvuArray, P_OFFSET, KP_OFFSET, OWNER_OFFSET,
                                       SHARED_OFFSET, UNIT_OFFSET, UNIT_STRIDE, UNIT_WORDS,
                                       UNIT_TILES, UNIT_LENGTH)


def array_for(vectors, case):
    cap = vectors["capacity"]
    return MvuArray(case["mvus"], words=cap["words"], tiles=cap["tiles"], nodes=cap["nodes"])


def run_phase(dut, phase):
    """Simulation process: starts a phase and waits for its end; the clocks it was busy."""
    yield dut.directions.storage.eq(phase["directions"])
    yield dut.start.re.eq(1)
    yield
    yield dut.start.re.eq(0)
    yield
    budget = 100000
    busy = 0
    while (yield dut.phase_busy):
        busy += 1
        budget -= 1
        assert budget > 0, "the phase did not finish"
        yield
    return busy


def results(dut, phase):
    d = phase["directions"]
    p_kp, kp_or = [], []
    for k in range(d):
        p_kp.append(str(testvectors.signed((yield dut.p_kp[k].status), 128)))
        kp_or.append((yield dut.kp_or[k].status))
    return p_kp, kp_or


class MvuArrayTest(unittest.TestCase):
    def check(self, phase, kp, p_kp, kp_or):
        d = phase["directions"]
        for row, (got, want) in enumerate(zip(kp, phase["kp"])):
            self.assertEqual(got[:d], want[:d], "Kp row %d" % row)
        self.assertEqual(p_kp, phase["p_kp"], "pᵀKp")
        self.assertEqual(kp_or, phase["kp_or"], "OR of |Kp|")

    def test_every_case_matches_the_kernel(self):
        vectors = testvectors.load()
        for case in vectors["cases"]:
            with self.subTest(case=case["name"]):
                started = time.time()
                self.run_case(vectors, case)
                print("  %s: %.1f s" % (case["name"], time.time() - started), file=sys.stderr)

    def run_case(self, vectors, case):
        dut = array_for(vectors, case)
        for m, unit in enumerate(dut.units):
            testvectors.init_unit(unit, case, m)
        depth = dut.nodes_depth
        dut.tables.owner.init = testvectors.padded(case["owner"], depth)
        dut.tables.shared.init = testvectors.padded(
            [testvectors.shared_entry(e) for e in case["shared"]], depth)
        got = []
        counts = []

        def bench():
            yield dut.n.storage.eq(case["n"])
            yield dut.shared_rows.storage.eq(len(case["shared"]))
            yield dut.kp_plain.storage.eq(0)
            for m, length in enumerate(dut.lengths):
                yield length.eq(testvectors.length(case, m))
            for k, phase in enumerate(case["phases"]):
                if k:
                    for unit in dut.units:
                        yield from testvectors.set_p(unit, phase["p"])
                busy = yield from run_phase(dut, phase)
                counts.append((busy, (yield dut.phases.status), (yield dut.cycles.status),
                               (yield dut.stalls.status)))
                kp = []
                for row, owner in enumerate(case["owner"]):
                    entry = yield dut.units[owner].kp.memory[row]
                    kp.append(testvectors.kp_lanes(entry))
                got.append((kp, *(yield from results(dut, phase))))

        run_simulation(dut, bench())
        for phase, result in zip(case["phases"], got):
            self.check(phase, *result)
        self.check_counts(counts)

    def check_counts(self, counts):
        """`phases`, `cycles` and `stalls` count over every phase since reset: the firmware
        reads them when it loads and drops a matrix, not per phase."""
        busy_total = 0
        stalls_before = 0
        for k, (busy, phases, cycles, stalls) in enumerate(counts):
            busy_total += busy
            self.assertEqual(phases, k + 1)
            self.assertEqual(cycles, busy_total, "the phases' clocks so far")
            self.assertGreaterEqual(stalls, stalls_before)
            stalls_before = stalls

    def test_a_case_loaded_and_read_through_the_bus(self):
        vectors = testvectors.load()
        # The smallest case with shared rows on several MVUs (every bus access takes clocks).
        case = min((c for c in vectors["cases"] if c["mvus"] > 1 and c["shared"]),
                   key=lambda c: sum(c["lengths"]) + c["n"])
        dut = array_for(vectors, case)
        bus = dut.bus
        got = []
        counts = []

        def write(byte_offset, value):
            yield from bus.write(byte_offset >> 2, value & 0xFFFFFFFF)

        def read(byte_offset):
            return (yield from bus.read(byte_offset >> 2))

        def bench():
            yield dut.n.storage.eq(case["n"])
            yield dut.shared_rows.storage.eq(len(case["shared"]))
            yield dut.kp_plain.storage.eq(0)
            for m in range(case["mvus"]):
                unit = UNIT_OFFSET + m * UNIT_STRIDE
                for i, (word, flags) in enumerate(case["words"][m]):
                    yield from write(unit + UNIT_WORDS + 8 * i, word)
                    yield from write(unit + UNIT_WORDS + 8 * i + 4, flags)
                for i, (row_base, col_base, mirror_base, mirrored) in enumerate(case["tiles"][m]):
                    yield from write(unit + UNIT_TILES + 8 * i, row_base | (col_base << 16))
                    yield from write(unit + UNIT_TILES + 8 * i + 4,
                                     mirror_base | (int(mirrored) << 31))
                yield from write(unit + UNIT_LENGTH, case["lengths"][m])
                # The program reads back as written.
                for i, (word, flags) in enumerate(case["words"][m][:8]):
                    self.assertEqual((yield from read(unit + UNIT_WORDS + 8 * i)), word)
                    self.assertEqual((yield from read(unit + UNIT_WORDS + 8 * i + 4)), flags)
            for row, owner in enumerate(case["owner"]):
                yield from write(OWNER_OFFSET + 4 * row, owner)
            for i, entry in enumerate(case["shared"]):
                yield from write(SHARED_OFFSET + 4 * i, testvectors.shared_entry(entry))
            for k, phase in enumerate(case["phases"]):
                for i, lanes in enumerate(phase["p"]):
                    for lane, v in enumerate(lanes):
                        yield from write(P_OFFSET + 16 * i + 4 * lane, v)
                # p reads back, padding lane included.
                for i, lanes in enumerate(phase["p"][:4]):
                    back = []
                    for lane in range(4):
                        value = yield from read(P_OFFSET + 16 * i + 4 * lane)
                        back.append(testvectors.signed(value, 32))
                    self.assertEqual(back, lanes)
                busy = yield from run_phase(dut, phase)
                counts.append((busy, (yield dut.phases.status), (yield dut.cycles.status),
                               (yield dut.stalls.status)))
                kp = []
                for row in range(case["n"]):
                    words = []
                    for w in range(6):
                        words.append((yield from read(KP_OFFSET + 24 * row + 4 * w)))
                    kp.append([testvectors.signed(words[2 * l] | (words[2 * l + 1] << 32), 64)
                               for l in range(3)])
                got.append((kp, *(yield from results(dut, phase))))
            # Kp behaves as memory between phases: a byte written reads back.
            yield from bus.write((KP_OFFSET + 24 * 3 + 8) >> 2, 0xAB << 16, sel=0b0100)
            word = yield from read(KP_OFFSET + 24 * 3 + 8)
            self.assertEqual((word >> 16) & 0xFF, 0xAB)

        run_simulation(dut, bench())
        for phase, result in zip(case["phases"], got):
            self.check(phase, *result)
        self.check_counts(counts)


if __name__ == "__main__":
    unittest.main()
