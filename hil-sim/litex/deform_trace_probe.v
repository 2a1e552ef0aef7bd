// deform's VexRiscv pipeline probe for Verilator traces (deform_soc.py --trace).
//
// Copies the VexRiscv's pipeline arbitration, hazard and bus signals out of the CPU (Verilator
// resolves the hierarchical references `sim.VexRiscv.*`; the names are those of
// pythondata-cpu-vexriscv's generated VexRiscv_IMAC.v) into this module, so that the CPU's own
// thousands of signals need not be traced (deform_trace.vlt turns them off).
//
// It also drives the SoC's `sim_trace` pin, which gates LiteX's trace dump: the dump starts when
// the instruction at `start_pc` retires for the (`skip` + 1)-th time and lasts `cycles` clocks.
// The three numbers come from `trace_window.init` in the simulator's working folder
// ($readmemh: start_pc, skip, cycles, one hex word a line), written by the run (hil-sim
// litex.rs), so one Verilated SoC traces any window of any firmware. Without the file, or with
// `cycles` 0, nothing is dumped.
module deform_trace_probe (
  input  wire clk,
  output reg  trace_on
);
  reg [31:0] window [0:2];
  reg [31:0] seen;
  reg [31:0] left;
  reg        done;
  initial begin
    window[0] = 32'd0;
    window[1] = 32'd0;
    window[2] = 32'd0;
    $readmemh("trace_window.init", window);
    seen = 32'd0;
    left = 32'd0;
    done = 1'b0;
    trace_on = 1'b0;
  end

  // writeBack: the retiring stage.
  wire        wb_valid = sim.VexRiscv.writeBack_arbitration_isValid;
  wire        wb_fire = sim.VexRiscv.writeBack_arbitration_isFiring;
  wire        wb_stuck = sim.VexRiscv.writeBack_arbitration_isStuck;
  wire        wb_halt = sim.VexRiscv.writeBack_arbitration_haltItself;
  wire        wb_flush = sim.VexRiscv.writeBack_arbitration_flushIt;
  wire [31:0] wb_pc = sim.VexRiscv.writeBack_PC;
  // memory: the multiplier's second step; MulDivIterative halts it while dividing.
  wire        mem_valid = sim.VexRiscv.memory_arbitration_isValid;
  wire        mem_stuck = sim.VexRiscv.memory_arbitration_isStuck;
  wire        mem_halt = sim.VexRiscv.memory_arbitration_haltItself;
  wire        mem_remove = sim.VexRiscv.memory_arbitration_removeIt;
  wire [31:0] mem_instr = sim.VexRiscv.memory_INSTRUCTION;
  // execute: the data cache's halt (l343) and refill wait (l359), CSR side effects.
  wire        ex_valid = sim.VexRiscv.execute_arbitration_isValid;
  wire        ex_stuck = sim.VexRiscv.execute_arbitration_isStuck;
  wire        ex_halt = sim.VexRiscv.execute_arbitration_haltItself;
  wire        ex_hbo = sim.VexRiscv.execute_arbitration_haltByOther;
  wire        ex_remove = sim.VexRiscv.execute_arbitration_removeIt;
  wire        ex_dcache = sim.VexRiscv.when_DBusCachedPlugin_l343;
  wire [31:0] ex_instr = sim.VexRiscv.execute_INSTRUCTION;
  // decode: the hazard plugin's stall, split by the stage holding the unbypassable result.
  wire        dec_valid = sim.VexRiscv.decode_arbitration_isValid;
  wire        dec_stuck = sim.VexRiscv.decode_arbitration_isStuck;
  wire        dec_halt = sim.VexRiscv.decode_arbitration_haltItself;
  wire        dec_hbo = sim.VexRiscv.decode_arbitration_haltByOther;
  wire        dec_remove = sim.VexRiscv.decode_arbitration_removeIt;
  wire        hazard = sim.VexRiscv.when_HazardSimplePlugin_l113;
  wire        haz_ex = sim.VexRiscv.when_HazardSimplePlugin_l57_2
                       && sim.VexRiscv.when_HazardSimplePlugin_l58_2
                       && ((sim.VexRiscv.when_HazardSimplePlugin_l48_2
                            && !sim.VexRiscv.when_HazardSimplePlugin_l105)
                           || (sim.VexRiscv.when_HazardSimplePlugin_l51_2
                               && !sim.VexRiscv.when_HazardSimplePlugin_l108));
  wire        haz_mem = sim.VexRiscv.when_HazardSimplePlugin_l57_1
                        && sim.VexRiscv.when_HazardSimplePlugin_l58_1
                        && ((sim.VexRiscv.when_HazardSimplePlugin_l48_1
                             && !sim.VexRiscv.when_HazardSimplePlugin_l105)
                            || (sim.VexRiscv.when_HazardSimplePlugin_l51_1
                                && !sim.VexRiscv.when_HazardSimplePlugin_l108));
  wire        csr_block = sim.VexRiscv.CsrPlugin_pipelineLiberator_active;
  // Jumps: predicted in decode, resolved in memory (a flush of decode and execute).
  wire        jump_dec = sim.VexRiscv.IBusCachedPlugin_predictionJumpInterface_valid;
  wire        jump_mem = sim.VexRiscv.BranchPlugin_jumpInterface_valid;
  // The buses: an instruction-cache line refill, a data-cache refill or a written word.
  wire        ibus_cyc = sim.VexRiscv.iBusWishbone_CYC;
  wire        dbus_cyc = sim.VexRiscv.dBusWishbone_CYC;
  wire        dbus_we = sim.VexRiscv.dBusWishbone_WE;
  wire        dbus_ack = sim.VexRiscv.dBusWishbone_ACK;

  always @(posedge clk) begin
    if (!done && !trace_on && window[2] != 32'd0 && wb_fire && wb_pc == window[0]) begin
      if (seen == window[1]) begin
        trace_on <= 1'b1;
        left <= window[2];
      end
      seen <= seen + 32'd1;
    end
    if (trace_on) begin
      if (left <= 32'd1) begin
        trace_on <= 1'b0;
        done <= 1'b1;
      end
      left <= left - 32'd1;
    end
  end
endmodule
