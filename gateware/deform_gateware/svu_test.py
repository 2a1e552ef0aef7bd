"""The SVU in Migen's simulator against the portable SVU's vectors (``svu`` in the vectors file,
from ``hil-sim/tests/hil/gateware/svu_vectors.rs``): pass R and pass XP on each direction, with
plans as hart 0 makes them and with any plan the passes accept, full-range and zero vectors,
extreme elements, squares that wrap their block, and lengths around a block of 16.

p and Kp come from block RAMs beside the unit, as the MVU array's memories will serve them; r
and x are the unit's own. Every case checks every lane of every element (the other directions
must stay as they were), Σr² and the three ORs."""

import sys
import time
import unittest

from migen import Module

from deform_gateware.simulation import run_simulation

from deform_gateware import testvectors
from deform_gateware.bram import Bram
from deform_gateware.mvu import LANES, P_BITS, SUM_BITS
from deform_gateware.svu import Svu

MASK32 = (1 << 32) - 1
MASK64 = (1 << 64) - 1

REGISTERS = ("pass_xp", "r_mult", "kp_right", "kp_shift", "r_keep", "r_left", "r_right",
             "p_shift", "x_update", "x_mult", "x_left", "x_right", "p_update", "p_mult",
             "r_into_p_left", "r_into_p_right")


class Bench(Module):
    """The SVU with p and Kp memories of the MVU array's shapes on its ports."""

    def __init__(self, nodes):
        self.submodules.svu = svu = Svu(nodes)
        self.submodules.p = p = Bram(LANES * P_BITS, nodes)
        self.submodules.kp = kp = Bram(LANES * SUM_BITS, nodes)
        self.comb += [
            p.read[0].adr.eq(svu.p_read.adr), svu.p_read.dat.eq(p.read[0].dat),
            p.adr.eq(svu.p_write.adr), p.dat_w.eq(svu.p_write.dat_w),
            p.we.eq(svu.p_write.we),
            kp.read[0].adr.eq(svu.kp_read.adr), svu.kp_read.dat.eq(kp.read[0].dat),
        ]


def kp_entry(sums):
    return sum((v & MASK64) << (SUM_BITS * k) for k, v in enumerate(sums))


def p_lanes(entry):
    return [testvectors.signed(entry >> (P_BITS * k), P_BITS) for k in range(LANES)]


def load(bench, case):
    """Simulation process: the case's vectors into the memories, its plan into the registers."""
    svu, nodes = bench.svu, bench.svu.nodes_depth
    for i in range(case["n"]):
        for d in range(LANES):
            yield svu.r.memory[d * nodes + i].eq(case["r"][i][d] & MASK32)
            yield svu.x.memory[d * nodes + i].eq(case["x"][i][d] & MASK32)
        yield bench.p.memory[i].eq(testvectors.p_entry(case["p"][i]))
        yield bench.kp.memory[i].eq(kp_entry(case["kp"][i]))
    registers = case["registers"]
    for name in REGISTERS:
        csr = getattr(svu, name)
        yield csr.storage.eq(registers.get(name, 0) & ((1 << len(csr.storage)) - 1))
    yield svu.n.storage.eq(case["n"])
    yield svu.direction.storage.eq(case["direction"])


def run_pass(bench, case):
    """Simulation process: one pass; returns what the unit left (as the vectors name it)."""
    svu, nodes = bench.svu, bench.svu.nodes_depth
    yield from load(bench, case)
    yield svu.start.re.eq(1)
    yield
    yield svu.start.re.eq(0)
    yield
    budget = case["n"] + svu.latency + 4
    while (yield svu.busy.status):
        budget -= 1
        assert budget > 0, "the pass did not finish in n + latency clocks"
        yield
    n = case["n"]
    got = {"r": [], "x": [], "p": []}
    for i in range(n):
        for name, memory in (("r", svu.r.memory), ("x", svu.x.memory)):
            lanes = []
            for d in range(LANES):
                lanes.append(testvectors.signed((yield memory[d * nodes + i]), 32))
            got[name].append(lanes)
        got["p"].append(p_lanes((yield bench.p.memory[i])))
    got["rr"] = str((yield svu.rr.status))
    for name in ("r_or", "x_or", "p_or"):
        got[name] = yield getattr(svu, name).status
    return got


class SvuTest(unittest.TestCase):
    def test_every_pass_matches_the_portable_svu(self):
        vectors = testvectors.load()["svu"]
        cases = vectors["cases"]
        self.assertTrue(cases)
        bench = Bench(vectors["nodes"])
        results = []

        def process():
            for case in cases:
                results.append((yield from run_pass(bench, case)))

        started = time.time()
        run_simulation(bench, process())
        print("  %d SVU passes: %.1f s" % (len(cases), time.time() - started), file=sys.stderr)
        self.assertEqual(len(results), len(cases))
        for case, got in zip(cases, results):
            want = case["want"]
            with self.subTest(case=case["name"]):
                for name in ("r", "x"):
                    self.assertEqual(got[name], want[name], name)
                self.assertEqual(got["p"], [lanes[:LANES] for lanes in want["p"]], "p")
                for name in ("rr", "r_or", "x_or", "p_or"):
                    self.assertEqual(got[name], want[name], name)


if __name__ == "__main__":
    unittest.main()
