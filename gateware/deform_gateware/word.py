"""The MVU instruction word of thesis ch. 4.2.1, decoded exactly as ``shared/src/word.rs``::

     31   30   29 ........ 21   20 ............................ 0
    [EM] [ER] [ column, 9 bit ] [ value, 21-bit two's complement ]

EM ends a tile (the thesis's matrix), ER a row. The word memory of a hardware MVU holds 36-bit
entries: the word, and above it (bits 32..35) the write-back flags of an ER word, laid out by
``target-core/src/mvu_program.rs`` (``flags``).
"""

from migen import Module, Signal

EM_BIT = 31
ER_BIT = 30
COLUMN_SHIFT = 21
COLUMN_BITS = 9
VALUE_BITS = 21
VALUE_MIN = -(1 << (VALUE_BITS - 1))
VALUE_MAX = (1 << (VALUE_BITS - 1)) - 1

# The write-back flags (mvu_program.rs, `flags`), as bit positions within the flag field.
FIRST_OWN = 0
LAST_OWN = 1
FIRST_MIRROR = 2
LAST_MIRROR = 3
FLAG_BITS = 4
ENTRY_BITS = 32 + FLAG_BITS


class InstructionWord(Module):
    """Combinational decoder of one word-memory entry (``entry``: 36 bits)."""

    def __init__(self):
        self.entry = Signal(ENTRY_BITS)
        self.em = Signal()
        self.er = Signal()
        self.column = Signal(COLUMN_BITS)
        self.value = Signal((VALUE_BITS, True))
        self.flags = Signal(FLAG_BITS)

        self.comb += [
            self.em.eq(self.entry[EM_BIT]),
            self.er.eq(self.entry[ER_BIT]),
            self.column.eq(self.entry[COLUMN_SHIFT:COLUMN_SHIFT + COLUMN_BITS]),
            # Assigning the 21 low bits to a signed 21-bit signal sign-extends them wherever the
            # value is used, as `Word::raw_value` does.
            self.value.eq(self.entry[0:VALUE_BITS]),
            self.flags.eq(self.entry[32:32 + FLAG_BITS]),
        ]


def encode(column, value, end_of_row=False, end_of_matrix=False, flags=0):
    """A word-memory entry, for testbenches (the program itself comes from Rust)."""
    assert 0 <= column < (1 << COLUMN_BITS) and VALUE_MIN <= value <= VALUE_MAX
    bits = (column << COLUMN_SHIFT) | (value & ((1 << VALUE_BITS) - 1))
    bits |= (end_of_row << ER_BIT) | (end_of_matrix << EM_BIT)
    return bits | (flags << 32)
