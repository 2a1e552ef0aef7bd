//! The dynamic step's drift bound term by term, for measuring it on the host (issue 19: which
//! term keeps a step from skipping its closing pass, and by how much). Compiled only with the
//! `testkit` feature (std), never in the firmware: each record is a name and its values (f64),
//! pushed to one process-wide list that a host program drains after each frame.

extern crate std;

use std::sync::Mutex;
use std::vec::Vec;

/// One recorded event: what it is and its values, in the order the recording site documents.
pub type Record = (&'static str, Vec<f64>);

static RECORDS: Mutex<Vec<Record>> = Mutex::new(Vec::new());

/// Appends a record.
pub fn record(what: &'static str, values: &[f64]) {
    if let Ok(mut list) = RECORDS.lock() {
        list.push((what, values.to_vec()));
    }
}

/// Every record since the last call, oldest first.
pub fn take() -> Vec<Record> {
    RECORDS
        .lock()
        .map(|mut l| core::mem::take(&mut *l))
        .unwrap_or_default()
}
