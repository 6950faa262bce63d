//! Per-pass GPU timing (`silvr bench-train --profile`): every compute pass is timed, by timestamp queries
//! where the device has `TIMESTAMP_QUERY`, otherwise by submitting and waiting for each pass on its own
//! (timed submits, native only). Passes are grouped by the caller's scope (e.g. "proposal 0") and the
//! kernel entry; each record also sums the bytes of the buffers the pass binds, an upper bound on the
//! memory it moves (a gather from a large table touches less). Off by default: no queries, no cost.

use std::sync::{Arc, Mutex};

/// How passes are timed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ProfileMode {
    /// Timestamp queries at the start and end of every compute pass (device time).
    Timestamps,
    /// Each pass submitted and waited for on its own (host time around the submit; includes submit cost).
    TimedSubmits,
}

/// Totals of one (scope, kernel entry) pair.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct PassTotals {
    pub calls: u64,
    pub seconds: f64,
    pub bytes: u64,
}

/// One row of a profile report.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PassRow {
    pub scope: String,
    pub pass: String,
    pub calls: u64,
    pub seconds: f64,
    pub bytes_bound: u64,
}

/// Capacity of the timestamp query set (two queries per pass).
pub(crate) const MAX_QUERIES: u32 = 4096;

pub(crate) struct ProfilerState {
    pub mode: ProfileMode,
    pub scope: String,
    /// Passes with timestamps written and not yet resolved: (key, bytes).
    pub pending: Vec<((String, String), u64)>,
    pub query_set: Option<wgpu::QuerySet>,
    /// Totals per (scope, pass), in first-seen order so the report follows the step (a few dozen keys).
    pub totals: Vec<((String, String), PassTotals)>,
}

/// Shared handle (clones of a [`super::Gpu`] share one profiler).
pub(crate) type Profiler = Arc<Mutex<Option<ProfilerState>>>;

impl ProfilerState {
    pub fn new(mode: ProfileMode, query_set: Option<wgpu::QuerySet>) -> Self {
        Self {
            mode,
            scope: String::new(),
            pending: Vec::new(),
            query_set,
            totals: Vec::new(),
        }
    }

    pub fn add(&mut self, key: (String, String), seconds: f64, bytes: u64) {
        let i = match self.totals.iter().position(|(k, _)| *k == key) {
            Some(i) => i,
            None => {
                self.totals.push((key, PassTotals::default()));
                self.totals.len() - 1
            }
        };
        let t = &mut self.totals[i].1;
        t.calls += 1;
        t.seconds += seconds;
        t.bytes += bytes;
    }

    pub fn rows(&self) -> Vec<PassRow> {
        self.totals
            .iter()
            .map(|(k, t)| PassRow {
                scope: k.0.clone(),
                pass: k.1.clone(),
                calls: t.calls,
                seconds: t.seconds,
                bytes_bound: t.bytes,
            })
            .collect()
    }
}
