//! The figures of a soak run: its samples, its fault marks, the slope of a series, and an SVG
//! picture of the run. Pure code: no I/O.

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

/// One sample of the gateway process and of the jobs, `t_s` seconds after the soak started.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Seconds since the soak started.
    pub t_s: f64,
    /// Resident memory of the gateway, KiB.
    pub rss_kib: u64,
    /// Share of one core since the previous sample, percent.
    pub cpu_pct: f64,
    /// Open file descriptors of the gateway.
    pub open_files: u64,
    /// Threads of the gateway.
    pub threads: u64,
    /// Jobs ended so far, by outcome (cumulative).
    pub jobs_completed: u64,
    /// Jobs failed so far (cumulative).
    pub jobs_failed: u64,
    /// Whether the gateway process was running at this sample (it is killed and restarted).
    pub gateway_up: bool,
}

/// A fault injected at `t_s`, of `kind` (e.g. "line-cut", "gateway-kill").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mark {
    /// Seconds since the soak started.
    pub t_s: f64,
    /// What was injected.
    pub kind: String,
}

/// Least-squares slope of `points` (x = seconds, y = value) in units per hour; None with fewer
/// than 2 distinct x. Points with a non-finite coordinate are left out.
pub fn slope_per_hour(points: &[(f64, f64)]) -> Option<f64> {
    let finite = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let pts: Vec<(f64, f64)> = points.iter().copied().filter(finite).collect();
    let first = pts.first()?.0;
    if pts.iter().all(|p| p.0 == first) {
        return None;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let (sxy, sxx) = pts.iter().fold((0.0, 0.0), |(sxy, sxx), &(x, y)| {
        (sxy + (x - mx) * (y - my), sxx + (x - mx) * (x - mx))
    });
    let slope = sxy / sxx * 3600.0;
    (sxx > 0.0 && slope.is_finite()).then_some(slope)
}

const W: f64 = 1000.0;
const H: f64 = 700.0;
const LEFT: f64 = 70.0;
const RIGHT: f64 = 980.0;
const TOPS: [f64; 3] = [80.0, 290.0, 500.0];
const PANEL_H: f64 = 150.0;
const MID: &str = r#" text-anchor="middle""#;
const MID_BIG: &str = r#" text-anchor="middle" font-size="16" font-weight="bold""#;
const END: &str = r#" text-anchor="end""#;
const BOLD: &str = r#" font-weight="bold""#;
const SERIES: &str = "#1f4e79";
const COMPLETED: &str = "#2ca02c";
const FAILED: &str = "#d62728";
/// Colours of fault kinds, by order of first appearance (green and red are the jobs').
const PALETTE: [&str; 8] = [
    "#9467bd", "#ff7f0e", "#17becf", "#e377c2", "#8c564b", "#bcbd22", "#7f7f7f", "#1f77b4",
];

/// The picture of a run, a standalone SVG document (1000 × 700, no external fonts, scripts or
/// links; "sans-serif"): three stacked panels on one time axis in minutes, resident memory
/// (MiB), CPU (% of a core), and jobs completed / failed (cumulative, with a legend). Each
/// fault mark is a thin vertical line across the panels, coloured by kind (palette order =
/// order of first appearance), with a legend of the kinds and their counts. Memory and CPU
/// break where `gateway_up` is false, as they do at non-finite values; samples and marks
/// without a finite time are left out. Every text, `title` included, is XML-escaped. Without
/// samples, the document says "no samples".
pub fn svg(title: &str, samples: &[Sample], marks: &[Mark]) -> String {
    let mut out = String::new();
    let _ = write!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" font-family="sans-serif" font-size="11">"#
    );
    out.push_str(r#"<rect width="100%" height="100%" fill="white"/>"#);
    text(&mut out, W / 2.0, 26.0, MID_BIG, title);

    let mut ordered: Vec<&Sample> = samples.iter().filter(|s| s.t_s.is_finite()).collect();
    ordered.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
    if ordered.is_empty() {
        text(&mut out, W / 2.0, H / 2.0, MID, "no samples");
        out.push_str("</svg>");
        return out;
    }
    let marks: Vec<&Mark> = marks.iter().filter(|m| m.t_s.is_finite()).collect();
    let mut kinds: Vec<(&str, usize)> = Vec::new();
    for m in &marks {
        match kinds.iter_mut().find(|(k, _)| *k == m.kind) {
            Some((_, n)) => *n += 1,
            None => kinds.push((&m.kind, 1)),
        }
    }
    let colour = |kind: &str| {
        let i = kinds.iter().position(|(k, _)| *k == kind).unwrap_or(0);
        PALETTE[i % PALETTE.len()]
    };

    let mib = |s: &Sample| s.rss_kib as f64 / 1024.0;
    let xs = ordered.iter().map(|s| s.t_s / 60.0);
    let x = axis(xs.chain(marks.iter().map(|m| m.t_s / 60.0)), true, false);
    let up = || ordered.iter().filter(|s| s.gateway_up);
    let jobs = ordered
        .iter()
        .flat_map(|s| [s.jobs_completed, s.jobs_failed]);
    let ys = [
        axis(up().map(|s| mib(s)), false, false),
        axis(up().map(|s| s.cpu_pct), true, false),
        axis(jobs.map(|n| n as f64), true, true),
    ];
    let names = [
        "resident memory (MiB)",
        "CPU (% of a core)",
        "jobs (cumulative)",
    ];
    for ((top, y), name) in TOPS.into_iter().zip(&ys).zip(names) {
        panel(&mut out, top, &x, y, name);
    }
    let bottom = TOPS[2] + PANEL_H;
    text(&mut out, (LEFT + RIGHT) / 2.0, H - 12.0, MID, "time (min)");

    for m in &marks {
        let min = m.t_s / 60.0;
        let Some(px) = fin(map(min, &x, LEFT, RIGHT)) else {
            continue;
        };
        let (top, c, kind) = (TOPS[0], colour(&m.kind), esc(&m.kind));
        let _ = write!(
            out,
            r#"<line class="mark" x1="{px:.1}" y1="{top}" x2="{px:.1}" y2="{bottom}" stroke="{c}" stroke-width="1" stroke-opacity="0.8"><title>{kind} at {min:.1} min</title></line>"#
        );
    }

    let point = |s: &Sample, v: f64, panel: usize| {
        let px = fin(map(s.t_s / 60.0, &x, LEFT, RIGHT))?;
        let top = TOPS[panel];
        Some((px, fin(map(v, &ys[panel], top + PANEL_H, top))?))
    };
    // Memory and CPU break where the gateway is down; the jobs go on (the cell counts them).
    let up_point = |s: &Sample, v: f64, panel| s.gateway_up.then(|| point(s, v, panel)).flatten();
    let it = || ordered.iter();
    let mem = path_d(it().map(|s| up_point(s, mib(s), 0)));
    let cpu = path_d(it().map(|s| up_point(s, s.cpu_pct, 1)));
    let done = path_d(it().map(|s| point(s, s.jobs_completed as f64, 2)));
    let failed = path_d(it().map(|s| point(s, s.jobs_failed as f64, 2)));
    let lines = [("memory", SERIES, mem), ("cpu", SERIES, cpu)];
    let jobs = [("completed", COMPLETED, done), ("failed", FAILED, failed)];
    for (class, stroke, d) in lines.into_iter().chain(jobs).filter(|l| !l.2.is_empty()) {
        let _ = write!(
            out,
            r#"<path class="{class}" d="{d}" fill="none" stroke="{stroke}" stroke-width="1.5" stroke-linejoin="round" stroke-linecap="round"/>"#
        );
    }

    // Jobs legend, above the jobs panel on the right.
    let y = TOPS[2] - 6.0;
    for (x0, name, stroke) in [(800.0, "completed", COMPLETED), (895.0, "failed", FAILED)] {
        key(&mut out, "job-key", x0, y, stroke);
        text(&mut out, x0 + 20.0, y, "", name);
    }

    // Fault legend, under the title; wraps when a row is full.
    if !kinds.is_empty() {
        let (mut x0, mut y) = (LEFT + 45.0, 46.0);
        text(&mut out, LEFT, y, "", "faults:");
        for (kind, n) in &kinds {
            let label = format!("{kind} ({n})");
            let w = 34.0 + 6.0 * label.chars().count() as f64;
            if x0 + w > RIGHT && x0 > LEFT + 45.0 {
                (x0, y) = (LEFT + 45.0, y + 13.0);
            }
            key(&mut out, "mark-key", x0, y, colour(kind));
            text(&mut out, x0 + 20.0, y, "", &label);
            x0 += w;
        }
    }
    out.push_str("</svg>");
    out
}

/// A value axis: its range, its ticks, and the decimals of their labels.
struct Axis {
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
    decimals: usize,
}

/// An axis over the finite `values` with "nice" ticks (1, 2, 5 × 10ⁿ); `zero` includes 0,
/// `integer` keeps the step at least 1.
fn axis(values: impl Iterator<Item = f64>, zero: bool, integer: bool) -> Axis {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite()) {
        (lo, hi) = (lo.min(v), hi.max(v));
    }
    if zero {
        (lo, hi) = (lo.min(0.0), hi.max(0.0));
    }
    if lo > hi {
        (lo, hi) = (0.0, 1.0);
    }
    if lo >= hi {
        let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 0.05 };
        let pad = if integer { pad.max(1.0) } else { pad };
        let zero_floor = zero && lo == 0.0;
        (lo, hi) = if zero_floor {
            (0.0, pad)
        } else {
            (lo - pad, hi + pad)
        };
    }
    let raw = (hi - lo) / 5.0;
    let mag = 10f64.powf(raw.log10().floor());
    let nice = [1.0, 2.0, 5.0]
        .into_iter()
        .find(|&n| raw / mag <= n)
        .unwrap_or(10.0);
    let step = if integer {
        (mag * nice).max(1.0)
    } else {
        mag * nice
    };
    // Whole steps from below `lo` to above `hi`; `+ 0.0` turns -0 into 0.
    let (k0, k1) = ((lo / step).floor(), (hi / step).ceil());
    let (a, b) = (k0 * step + 0.0, k1 * step + 0.0);
    let mut ticks = vec![lo, hi]; // the fallback when the steps fail (overflow, rounding)
    let mut decimals = 0;
    if step > 0.0 && (1.0..=50.0).contains(&(k1 - k0)) && a.is_finite() && b.is_finite() && a < b {
        ticks = (0..=(k1 - k0) as usize)
            .map(|i| (k0 + i as f64) * step + 0.0)
            .collect();
        decimals = (-step.log10() - 1e-9).ceil().clamp(0.0, 9.0) as usize;
        (lo, hi) = (a, b);
    }
    Axis {
        lo,
        hi,
        ticks,
        decimals,
    }
}

/// `v` on `axis` mapped linearly onto the pixels from `a` (axis.lo) to `b` (axis.hi).
fn map(v: f64, axis: &Axis, a: f64, b: f64) -> f64 {
    a + (v - axis.lo) / (axis.hi - axis.lo) * (b - a)
}

fn fin(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// A tick label: fixed decimals, or an exponent for very large values.
fn label(v: f64, decimals: usize) -> String {
    let big = v.abs() >= 1e7;
    if big {
        format!("{v:.2e}")
    } else {
        format!("{v:.decimals$}")
    }
}

/// One panel's frame, grid, ticks with labels (both axes) and name.
fn panel(out: &mut String, top: f64, x: &Axis, y: &Axis, name: &str) {
    let bottom = top + PANEL_H;
    let _ = write!(
        out,
        r##"<rect x="{LEFT}" y="{top}" width="{}" height="{PANEL_H}" fill="none" stroke="#888"/>"##,
        RIGHT - LEFT
    );
    let (tick_x, tick_y) = (LEFT - 4.0, bottom + 4.0);
    for (t, py) in y
        .ticks
        .iter()
        .filter_map(|&t| Some((t, fin(map(t, y, bottom, top))?)))
    {
        let _ = write!(
            out,
            r##"<line x1="{tick_x}" y1="{py:.1}" x2="{RIGHT}" y2="{py:.1}" stroke="#ddd"/>"##
        );
        text(out, LEFT - 6.0, py + 4.0, END, &label(t, y.decimals));
    }
    for (t, px) in x
        .ticks
        .iter()
        .filter_map(|&t| Some((t, fin(map(t, x, LEFT, RIGHT))?)))
    {
        let _ = write!(
            out,
            r##"<line x1="{px:.1}" y1="{top}" x2="{px:.1}" y2="{tick_y}" stroke="#eee"/>"##
        );
        text(out, px, bottom + 14.0, MID, &label(t, x.decimals));
    }
    text(out, LEFT, top - 6.0, BOLD, name);
}

/// A short coloured line, the key of a legend entry whose text starts at `x + 20`.
fn key(out: &mut String, class: &str, x: f64, y: f64, stroke: &str) {
    let (ky, x2) = (y - 4.0, x + 16.0);
    let _ = write!(
        out,
        r#"<line class="{class}" x1="{x:.1}" y1="{ky:.1}" x2="{x2:.1}" y2="{ky:.1}" stroke="{stroke}" stroke-width="2"/>"#
    );
}

/// A `<text>` element with `content` escaped; `attrs` are raw (with a leading space).
fn text(out: &mut String, x: f64, y: f64, attrs: &str, content: &str) {
    let c = esc(content);
    let _ = write!(out, r#"<text x="{x:.1}" y="{y:.1}"{attrs}>{c}</text>"#);
}

/// Path data of a polyline broken where a point is None: one "M" per run of points.
fn path_d(points: impl Iterator<Item = Option<(f64, f64)>>) -> String {
    let (mut d, mut run) = (String::new(), 0);
    for p in points.chain([None]) {
        if let Some((x, y)) = p {
            let cmd = if run == 0 { " M" } else { " L" };
            let _ = write!(d, "{cmd}{x:.1},{y:.1}");
            run += 1;
        } else {
            if run == 1 {
                d.push_str(" l0,0"); // a lone point still shows, as a dot (round caps)
            }
            run = 0;
        }
    }
    d.trim_start().to_owned()
}

/// `s` escaped for XML text and attributes; characters XML 1.0 forbids are dropped.
fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&apos;"),
            '\t' | '\n' | '\r' => o.push(c),
            c if c < ' ' || c == '\u{fffe}' || c == '\u{ffff}' => {}
            c => o.push(c),
        }
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t_s: f64, rss_kib: u64, up: bool, done: u64, failed: u64) -> Sample {
        Sample {
            t_s,
            rss_kib,
            cpu_pct: 12.5,
            open_files: 40,
            threads: 12,
            jobs_completed: done,
            jobs_failed: failed,
            gateway_up: up,
        }
    }

    /// Balanced tags, one root, every `&` an entity: enough of XML for what `svg` writes.
    fn assert_well_formed(s: &str) {
        let ents = ["&amp;", "&lt;", "&gt;", "&quot;", "&apos;"];
        for (i, _) in s.match_indices('&') {
            assert!(ents.iter().any(|e| s[i..].starts_with(e)), "bare & at {i}");
        }
        let (mut stack, mut roots, mut rest) = (Vec::new(), 0, s.trim());
        while let Some(i) = rest.find('<') {
            assert!(
                !stack.is_empty() || rest[..i].trim().is_empty(),
                "text outside the root"
            );
            let end = rest[i..].find('>').expect("unclosed tag") + i;
            let tag = &rest[i + 1..end];
            rest = &rest[end + 1..];
            assert!(
                !tag.contains('<') && tag.matches('"').count() % 2 == 0,
                "bad tag {tag}"
            );
            if let Some(name) = tag.strip_prefix('/') {
                assert_eq!(stack.pop(), Some(name), "unbalanced </{name}>");
                continue;
            }
            let name = tag.split([' ', '/']).next().unwrap_or("");
            assert!(!name.is_empty(), "no name in <{tag}>");
            roots += usize::from(stack.is_empty());
            if !tag.ends_with('/') {
                stack.push(name);
            }
        }
        assert!(
            stack.is_empty() && roots == 1 && rest.trim().is_empty(),
            "{stack:?} {roots}"
        );
    }

    /// The runs of the path of `class`: its "M" commands.
    fn runs(svg: &str, class: &str) -> usize {
        let start = format!(r#"class="{class}" d=""#);
        let d = &svg[svg.find(&start).expect("path") + start.len()..];
        let d = &d[..d.find('"').expect("closing quote")];
        d.split(' ').filter(|c| c.starts_with('M')).count()
    }

    fn mark(t_s: f64, kind: &str) -> Mark {
        let kind = kind.into();
        Mark { t_s, kind }
    }

    #[test]
    fn slope_of_flat_series_is_zero() {
        let pts: Vec<_> = (0..10).map(|i| (i as f64 * 5.0, 42.0)).collect();
        assert!(slope_per_hour(&pts).expect("slope").abs() < 1e-9);
    }

    #[test]
    fn slope_of_2x_per_second_is_7200_per_hour() {
        let pts: Vec<_> = (0..10).map(|i| (i as f64, 2.0 * i as f64)).collect();
        assert!((slope_per_hour(&pts).expect("slope") - 7200.0).abs() < 1e-6);
    }

    #[test]
    fn slope_needs_two_distinct_x() {
        assert_eq!(slope_per_hour(&[]), None);
        assert_eq!(slope_per_hour(&[(1.0, 1.0)]), None);
        assert_eq!(slope_per_hour(&[(3.0, 1.0), (3.0, 9.0)]), None);
        assert_eq!(
            slope_per_hour(&[(1.0, 1.0), (f64::NAN, 2.0), (2.0, f64::INFINITY)]),
            None
        );
        assert!(slope_per_hour(&[(0.0, 0.0), (f64::NAN, 5.0), (1.0, 1.0)]).is_some());
    }

    #[test]
    fn svg_of_empty_input_is_well_formed() {
        let out = svg("soak <empty>", &[], &[]);
        assert_well_formed(&out);
        assert!(out.contains("no samples"));
        assert!(out.contains("soak &lt;empty&gt;"));
    }

    #[test]
    fn svg_of_a_run_marks_legends_escapes_and_gaps() {
        let mut s: Vec<Sample> = (0..60)
            .map(|i| sample(i as f64 * 5.0, 100_000 + i * 10, true, i / 3, i / 20))
            .collect();
        for i in [20, 21, 40] {
            s[i].gateway_up = false; // two outages: the memory line has three runs
        }
        let marks = [
            mark(30.0, "line-cut"),
            mark(100.0, "gateway-kill"),
            mark(150.0, "line-cut"),
            mark(200.0, "gateway-kill"),
            mark(250.0, "line-cut"),
        ];
        let out = svg("soak <a&b>", &s, &marks);
        assert_well_formed(&out);
        assert_eq!(out.matches(r#"<line class="mark""#).count(), marks.len());
        assert!(out.contains(">line-cut (3)<"));
        assert!(out.contains(">gateway-kill (2)<"));
        assert_eq!(out.matches(r#"class="mark-key""#).count(), 2);
        assert!(out.contains("soak &lt;a&amp;b&gt;") && !out.contains("<a&b>"));
        assert_eq!(runs(&out, "memory"), 3);
        assert_eq!(runs(&out, "cpu"), 3);
        assert_eq!(runs(&out, "completed"), 1);
        assert_eq!(runs(&out, "failed"), 1);
        assert!(!out.contains(">no samples<"));
    }

    #[test]
    fn svg_survives_non_finite_values() {
        let mut s = vec![sample(0.0, 1, true, 0, 0), sample(5.0, 2, true, 1, 0)];
        s[1].cpu_pct = f64::NAN;
        s.push(sample(f64::INFINITY, 3, true, 2, 0));
        s.push(sample(10.0, u64::MAX, true, u64::MAX, 0));
        let out = svg("t\u{1}<", &s, &[mark(f64::NAN, "x<")]);
        assert_well_formed(&out);
        assert!(!out.contains("NaN") && !out.contains("inf") && !out.contains('\u{1}'));
        assert!(!out.contains(r#"class="mark""#));
        let only_nan = svg("t", &[sample(f64::NAN, 1, true, 0, 0)], &[]);
        assert!(only_nan.contains("no samples"));
    }
}
