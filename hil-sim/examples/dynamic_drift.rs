//! The dynamic needle's drift bound, step by step and term by term (issue 19): which term of
//! the bound keeps a step from accepting its residual without the closing MVU pass, and by how
//! much. The session runs in this process (target-core's portable loops, the firmware's
//! specification bit for bit, on 8 sequential "harts"), so its bound can be read: target-core's
//! `trace` (feature `testkit`) records the start's bound (`dynamics::start_drift`), every
//! iteration's update terms and each tolerance test (`cg::proves_tolerance`).
//!
//! ```text
//! cargo run --release -p deform-hil-sim --example dynamic_drift [-- --steps 300]
//! ```

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::time::Duration;

#[path = "../tests/hil/needle.rs"]
#[allow(dead_code)] // the tests use all of the fixture, this example part of it
mod needle;

use clap::Parser;
use deform_host::dynamics::resident::ResidentSetup;
use deform_host::dynamics::{DynamicSystem, StepMatrices};
use deform_host::encode::{EncodeOptions, Partition};
use deform_host::link::{Link, Port, Target, Timeouts};
use deform_shared::protocol::{TargetInfo, PROTOCOL_VERSION};
use deform_target_core::exec::Sequential;
use deform_target_core::session::Session;
use deform_target_core::testkit::OwnedStorage;
use deform_target_core::trace;
use deform_target_core::transport::{TargetLink, Tx};

#[derive(Parser)]
#[command(about = "Print the dynamic needle's drift bound per step, term by term")]
struct Args {
    #[arg(long, default_value_t = 300)]
    steps: u32,
    #[arg(long, default_value_t = 1e-5)]
    tol: f64,
}

/// The target's session and transport in this process: bytes written are handled at once and
/// the replies wait to be read.
struct InProcess {
    session: Session<'static, Sequential>,
    link: Box<TargetLink>,
    replies: VecDeque<u8>,
}

struct Outbox<'a>(&'a mut VecDeque<u8>);

impl Tx for Outbox<'_> {
    fn write(&mut self, frame: &[u8]) {
        self.0.extend(frame);
    }
}

impl Write for InProcess {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let InProcess {
            session,
            link,
            replies,
        } = self;
        for &byte in buf {
            link.feed(byte, &mut |r| session.handle(r), &mut Outbox(replies));
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

impl Read for InProcess {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.replies.is_empty() {
            return Err(io::ErrorKind::TimedOut.into());
        }
        let n = buf.len().min(self.replies.len());
        for (b, r) in buf.iter_mut().zip(self.replies.drain(..n)) {
            *b = r;
        }
        Ok(n)
    }
}

impl Port for InProcess {
    fn set_timeout(&mut self, _: Duration) -> io::Result<()> {
        Ok(())
    }
}

fn main() {
    let args = Args::parse();
    let layout = EncodeOptions {
        mvus: 8,
        partition: Partition::Rows,
        use_symmetry: true,
    };
    let needle = needle::DynamicNeedle::load(&layout);
    let (simulation, spec, setup) = (&needle.simulation, &needle.spec, &needle.setup);
    let h = 1e-3;
    let model = &setup.model;
    let system = DynamicSystem::new(model, spec).unwrap();
    let matrices = StepMatrices::new(&system, h, spec.scheme).unwrap();
    let resident =
        ResidentSetup::new(&system, &matrices, &setup.tools, &layout, args.tol, 500, 0).unwrap();
    let info = TargetInfo {
        protocol_version: PROTOCOL_VERSION,
        firmware_version: "in-process".try_into().unwrap(),
        harts: 8,
        word_capacity: 1 << 20,
        tile_capacity: 1 << 14,
        max_n: 4096,
        build_id: Default::default(),
    };
    let port = InProcess {
        session: OwnedStorage::leaked_session(info),
        link: Box::new(TargetLink::new()),
        replies: VecDeque::new(),
    };
    let mut target = Target::handshake(Link::new(port), Timeouts::default()).unwrap();
    resident.start(&mut target).unwrap();
    trace::take();
    println!("step it skip | start: 2e0 r1 d1 d0 shifts S.dv S.A = bound (unchecked) | updates r x | last test: |r| drift tol|b| allowed-drift");
    for i in 1..=args.steps {
        let spec_t = simulation.spec_at(&needle.model, f64::from(i) * h);
        let tool = vec![spec_t.prescribed[0].u.map(|v| f64::from(v as f32))];
        let report = ResidentSetup::frame(&mut target, &tool).unwrap();
        print_step(i, report.iterations, &trace::take());
    }
}

/// One line per step: the start's terms, the updates' sums, and the last tolerance test with
/// the drift a skip would have allowed (√(tol²‖b‖²/2 − ‖r‖²)).
fn print_step(i: u32, iterations: u16, records: &[trace::Record]) {
    let g = |v: f64| format!("{v:.2e}");
    let mut line = format!("{i:3} {iterations:2}");
    let (mut ur, mut ux) = (0.0, 0.0);
    let mut start = String::from(" | start -");
    let mut test = String::from(" | test -");
    let mut skip = "  ";
    for (what, v) in records {
        match *what {
            "start" => {
                start = format!(
                    " | start {} {} {} {} {} {} {} = {} ({})",
                    g(v[0]),
                    g(v[1]),
                    g(v[2]),
                    g(v[3]),
                    g(v[4]),
                    g(v[5]),
                    g(v[6]),
                    g(v[7]),
                    v[8]
                )
            }
            "update" => {
                ur += v[0];
                ux += v[1];
            }
            "proven" => {
                let allowed = (v[2] * v[2] / 2.0 - v[0] * v[0]).max(0.0).sqrt();
                skip = if v[3] != 0.0 { " S" } else { " -" };
                test = format!(
                    " | test {} {} {} allowed {} ratio {:.2}",
                    g(v[0]),
                    g(v[1]),
                    g(v[2]),
                    g(allowed),
                    v[1] / allowed
                );
            }
            _ => {}
        }
    }
    line.push_str(skip);
    line.push_str(&start);
    line.push_str(&format!(" | upd {} {}", g(ur), g(ux)));
    line.push_str(&test);
    println!("{line}");
}
