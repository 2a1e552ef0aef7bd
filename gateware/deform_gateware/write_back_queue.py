"""The MVU's write-back queue: the sums of finished rows, waiting for the write-back.

Migen's ``SyncFIFOBuffered`` (a ``SyncFIFO`` with a registered read, and its head in that
register) with one change for the clock: the memory's pop (``fifo.re``, which also steps the
level counter) is decided from registers of its own. In ``SyncFIFOBuffered`` it hangs on the
head's valid bit, which the MVU's write-back stage S reads too and which the placer therefore
puts among S's ~200 bits, far from the queue: the pop's path went from the level counter out to
S and back (measured: 123.7 and 126.5 MHz at two seeds of one MVU alone). Here the pop sees
``head_empty``, the valid bit's complement kept as a register of its own (complemented, so that
Yosys does not merge the two), and ``re``, which the MVU gives as a register too.
"""

from migen import Module, Signal, If
from migen.genlib.fifo import SyncFIFO


class WriteBackQueue(Module):
    """``SyncFIFOBuffered``'s interface (``din``, ``we``, ``dout``, ``readable``, ``re``, ``level``,
    ``fifo``) and behaviour, clock for clock."""

    def __init__(self, width, depth):
        self.submodules.fifo = fifo = SyncFIFO(width, depth, fwft=False)
        self.din = fifo.din
        self.we = fifo.we
        self.dout = fifo.dout
        self.readable = Signal()      # the head register holds an entry
        self.re = Signal()            # take the head
        self.level = Signal(max=depth + 2)

        head_empty = Signal(reset=1)  # ~readable, for the memory's pop alone
        self.comb += [
            fifo.re.eq(fifo.readable & (head_empty | self.re)),
            self.level.eq(fifo.level + self.readable),
        ]
        self.sync += If(fifo.re,
            self.readable.eq(1), head_empty.eq(0),
        ).Elif(self.re,
            self.readable.eq(0), head_empty.eq(1))
