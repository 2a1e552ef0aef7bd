"""deform's gateware: the thesis's matrix-vector units (MVUs) for a LiteX SoC, in Migen.

One module per hardware unit, each with its testbench beside it (``*_test.py``):

- ``word``: the MVU instruction word (EM, ER, column, value), exactly as ``shared/src/word.rs``.
- ``multiplier``: signed multipliers pipelined in 18x18 partial products (ECP5 MULT18X18D).
- ``mvu``: one MVU: word and tile memories, its copies of p, its Kp memory, the word pipeline
  (fetch, decode, multiply-accumulate), the row write-back and pᵀKp.
- ``mvu_array``: the MVUs side by side with the shared p and Kp apertures the CPU addresses,
  the shared-row reduction and the phase's control and status registers.
"""
