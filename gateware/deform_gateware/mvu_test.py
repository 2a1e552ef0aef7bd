"""One MVU alone, in Migen's simulator, against the portable kernel's vectors: every case that
runs on a single MVU (every split, mirroring and direction count; rows at the edge of exact
sums), two phases each, the second on the Kp memory the first left behind."""

import unittest

from deform_gateware.simulation import run_simulation

from deform_gateware import testvectors
from deform_gateware.mvu import Mvu


def run_phase(unit, case, phase, first):
    """Simulation process: one phase; returns (Kp rows, pᵀKp per direction, OR per direction)."""
    n = case["n"]
    if not first:
        yield from testvectors.set_p(unit, phase["p"])
    yield unit.last_row.eq(n - 1)
    yield unit.directions.eq(phase["directions"])
    yield unit.length.eq(testvectors.length(case, 0))
    yield unit.start.eq(1)
    yield
    yield unit.start.eq(0)
    yield
    budget = 40 * testvectors.length(case, 0) + 200
    while (yield unit.busy):
        budget -= 1
        assert budget > 0, "the MVU did not finish"
        yield
    kp = []
    for row in range(n):
        kp.append(testvectors.kp_lanes((yield unit.kp.memory[row])))
    d = phase["directions"]
    p_kp, kp_or = [], []
    for lane in range(d):
        low = yield unit.p_kp_low[lane]
        high = yield unit.p_kp_high[lane]
        p_kp.append(str(low + (high << 32)))
        kp_or.append((yield unit.kp_or[lane]))
    return kp, p_kp, kp_or


class MvuTest(unittest.TestCase):
    def test_single_mvu_cases_match_the_kernel(self):
        vectors = testvectors.load()
        cap = vectors["capacity"]
        cases = [c for c in vectors["cases"] if c["mvus"] == 1]
        self.assertTrue(cases)
        for case in cases:
            with self.subTest(case=case["name"]):
                unit = Mvu(cap["words"], cap["tiles"], cap["nodes"])
                testvectors.init_unit(unit, case, 0)
                results = []

                def bench():
                    for k, phase in enumerate(case["phases"]):
                        results.append((yield from run_phase(unit, case, phase, k == 0)))

                run_simulation(unit, bench())
                for phase, (kp, p_kp, kp_or) in zip(case["phases"], results):
                    d = phase["directions"]
                    for row, (got, want) in enumerate(zip(kp, phase["kp"])):
                        self.assertEqual(got[:d], want[:d], "Kp row %d" % row)
                    self.assertEqual(p_kp, phase["p_kp"], "pᵀKp")
                    self.assertEqual(kp_or, phase["kp_or"], "OR of |Kp|")


if __name__ == "__main__":
    unittest.main()
