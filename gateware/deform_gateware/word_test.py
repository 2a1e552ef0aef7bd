"""The instruction-word decoder against ``shared::word``'s own decoding of edge and random words."""

import unittest

from deform_gateware.simulation import run_simulation

from deform_gateware import testvectors
from deform_gateware.word import InstructionWord


class InstructionWordTest(unittest.TestCase):
    def test_fields_as_shared_word_decodes_them(self):
        rows = testvectors.load()["decoded_words"]
        dut = InstructionWord()
        got = []

        def bench():
            for bits, *_ in rows:
                yield dut.entry.eq(bits | (0b1010 << 32))
                yield
                got.append([bits, (yield dut.column), (yield dut.value), bool((yield dut.er)),
                            bool((yield dut.em))])
                self.assertEqual((yield dut.flags), 0b1010)

        run_simulation(dut, bench())
        self.assertEqual(got, rows)


if __name__ == "__main__":
    unittest.main()
