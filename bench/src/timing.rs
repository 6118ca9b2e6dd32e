//! Timing helpers: batches long enough to beat the clock, interleaved cases, best of rounds.
//!
//! The machines these run on are shared and noisy, so cases that are compared are measured in
//! the same run, interleaved round by round, and each reports its best (minimum) batch.

use std::time::{Duration, Instant};

/// Seconds per call of `f`: runs `f` in a batch until at least `batch` has passed.
pub fn per_call(f: &mut dyn FnMut(), batch: Duration) -> f64 {
    let t0 = Instant::now();
    let mut n = 0u64;
    loop {
        f();
        n += 1;
        let e = t0.elapsed();
        if e >= batch {
            return e.as_secs_f64() / n as f64;
        }
    }
}

/// A named case to time.
pub struct Case<'a> {
    pub name: String,
    pub f: Box<dyn FnMut() + 'a>,
}

impl<'a> Case<'a> {
    pub fn new(name: impl Into<String>, f: impl FnMut() + 'a) -> Self {
        Case {
            name: name.into(),
            f: Box::new(f),
        }
    }
}

/// Times every case: one warm-up call each, then `rounds` rounds in which each case runs one
/// batch of at least `batch`; returns the best seconds per call of each case, in order.
pub fn interleaved(cases: &mut [Case<'_>], rounds: usize, batch: Duration) -> Vec<f64> {
    for c in cases.iter_mut() {
        (c.f)();
    }
    let mut best = vec![f64::INFINITY; cases.len()];
    for _ in 0..rounds {
        for (k, c) in cases.iter_mut().enumerate() {
            best[k] = best[k].min(per_call(&mut c.f, batch));
        }
    }
    best
}

/// Wall time of one call of `f`, in seconds, and its result.
pub fn once<R>(f: impl FnOnce() -> R) -> (f64, R) {
    let t0 = Instant::now();
    let r = f();
    (t0.elapsed().as_secs_f64(), r)
}

/// Formats seconds with a unit (ns, us, ms, s).
pub fn fmt_s(s: f64) -> String {
    if s < 1e-6 {
        format!("{:.0} ns", s * 1e9)
    } else if s < 1e-3 {
        format!("{:.1} us", s * 1e6)
    } else if s < 1.0 {
        format!("{:.2} ms", s * 1e3)
    } else {
        format!("{s:.2} s")
    }
}

/// A short description of the machine: CPU model, cores, memory, kernel.
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let mem = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("MemTotal")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|k| k.parse::<f64>().ok())
            })
        })
        .map_or(String::new(), |kb| {
            format!(", {:.0} GB RAM", kb / 1048576.0)
        });
    let kernel = std::fs::read_to_string("/proc/sys/kernel/osrelease")
        .map_or(String::new(), |k| format!(", Linux {}", k.trim()));
    format!("{cpu}, {cores} cores available{mem}{kernel}")
}

fn unix_secs() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64
}

/// The current time (UTC) as `YYYY-MM-DDTHH:MM:SSZ`.
pub fn now_iso() -> String {
    let s = unix_secs().rem_euclid(86400);
    format!(
        "{}T{:02}:{:02}:{:02}Z",
        today(),
        s / 3600,
        s / 60 % 60,
        s % 60
    )
}

/// Today's date (UTC) as YYYY-MM-DD, from the system clock.
pub fn today() -> String {
    let days = unix_secs().div_euclid(86400);
    // civil from days (Howard Hinnant's algorithm)
    let z = days + 719468;
    let era = z.div_euclid(146097);
    let doe = z - era * 146097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    format!("{:04}-{:02}-{:02}", if m <= 2 { y + 1 } else { y }, m, d)
}

/// Peak resident set size of this process in MB (VmHWM of /proc/self/status).
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|k| k.parse::<f64>().ok())
            })
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// The 1-minute load average (other processes compete for the cores).
pub fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_default()
}

/// Waits (up to `max_wait` seconds, polling every 5 s) until the 1-minute load average is
/// below `limit`; returns the load average it stopped at. Benchmarks call it when asked
/// (`--wait-load L`) so that parallel timings are not taken while other builds run.
pub fn wait_for_load(limit: f64, max_wait: f64) -> f64 {
    let t0 = std::time::Instant::now();
    loop {
        let l: f64 = loadavg().parse().unwrap_or(0.0);
        if l < limit || t0.elapsed().as_secs_f64() > max_wait {
            return l;
        }
        std::thread::sleep(std::time::Duration::from_secs(5));
    }
}
