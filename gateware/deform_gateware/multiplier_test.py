"""The pipelined multiplier against Python's exact integer products, random and extreme."""

import random
import unittest

from deform_gateware.simulation import run_simulation

from deform_gateware.multiplier import Multiplier


def products(a_width, b_width, count, seed):
    rng = random.Random(seed)
    a_lim, b_lim = 1 << (a_width - 1), 1 << (b_width - 1)
    edges = [(-a_lim, -b_lim), (-a_lim, b_lim - 1), (a_lim - 1, -b_lim), (a_lim - 1, b_lim - 1),
             (0, -b_lim), (-1, -1), (1, -1)]
    rand = [(rng.randrange(-a_lim, a_lim), rng.randrange(-b_lim, b_lim)) for _ in range(count)]
    return edges + rand


class MultiplierTest(unittest.TestCase):
    def check(self, a_width, b_width):
        dut = Multiplier(a_width, b_width)
        cases = products(a_width, b_width, 200, a_width * 100 + b_width)
        got = []

        def drive():
            for a, b in cases:
                yield dut.a.eq(a)
                yield dut.b.eq(b)
                yield dut.valid_in.eq(1)
                yield
            yield dut.valid_in.eq(0)
            for _ in range(dut.latency + 2):
                yield

        def watch():
            while len(got) < len(cases):
                if (yield dut.valid):
                    got.append((yield dut.p))
                yield

        run_simulation(dut, [drive(), watch()])
        self.assertEqual(got, [a * b for a, b in cases])

    def test_instruction_value_times_p(self):
        # The MVU's multiply-accumulate: a 21-bit word value times a 32-bit p lane.
        self.check(21, 32)

    def test_p_times_half_of_kp(self):
        # pᵀKp: a p lane times 33 bits (a zero- or sign-extended half of a 64-bit row sum).
        self.check(32, 33)

    def test_top_slices_of_three_and_five_bits_in_logic(self):
        # Odd-width top slices: the sign bit's term stands alone.
        self.check(20, 32)
        self.check(22, 32)

    def test_operands_in_one_block(self):
        self.check(18, 18)


if __name__ == "__main__":
    unittest.main()
