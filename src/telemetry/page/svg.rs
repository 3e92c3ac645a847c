//! One task's pool drawn as inline SVG: a row per trajectory in score order (best first),
//! its score and its length as bars, its actions as a strip: a colour per discrete action
//! (an 8-bit bitmap embedded in the SVG, one pixel column per action or per group of
//! actions when a trajectory is longer than the strip is wide), or a sparkline per
//! dimension for a continuous task.

use std::fmt::Write;

use crate::core::{ActionSeq, Pool};

/// Colours of discrete actions 0, 1, …; action `a` takes `PALETTE[a % 12]`.
pub(super) const PALETTE: [[u8; 3]; 12] = [
    [0x1f, 0x77, 0xb4],
    [0xff, 0x7f, 0x0e],
    [0x2c, 0xa0, 0x2c],
    [0xd6, 0x27, 0x28],
    [0x94, 0x67, 0xbd],
    [0x8c, 0x56, 0x4b],
    [0xe3, 0x77, 0xc2],
    [0x7f, 0x7f, 0x7f],
    [0xbc, 0xbd, 0x22],
    [0x17, 0xbe, 0xcf],
    [0x39, 0x3b, 0x79],
    [0xad, 0x49, 0x4a],
];

const SCORE_X: f64 = 0.0;
const SCORE_W: f64 = 180.0;
const LEN_X: f64 = 190.0;
const LEN_W: f64 = 120.0;
const STRIP_X: f64 = 320.0;
/// The strip's width in pixels: at most this many action columns per trajectory.
const STRIP_W: usize = 600;
const TOP: f64 = 18.0;
/// Points of one continuous sparkline at most.
const SPARK_POINTS: usize = 48;

/// The pool's rows in score order, best first (ties: older first).
fn ranked(pool: &Pool) -> Vec<usize> {
    let t = pool.trajectories();
    let mut order: Vec<usize> = (0..t.len()).collect();
    order.sort_by(|&a, &b| {
        t[b].score
            .total_cmp(&t[a].score)
            .then(t[a].seq.cmp(&t[b].seq))
    });
    order
}

fn row_height(n: usize) -> f64 {
    match n {
        0..=40 => 14.0,
        41..=150 => 6.0,
        151..=400 => 3.0,
        _ => 2.0,
    }
}

/// The SVG of `pool`.
pub(super) fn pool_svg(pool: &Pool) -> String {
    let t = pool.trajectories();
    let n = t.len();
    let h = row_height(n);
    let order = ranked(pool);
    let (lo, hi) = pool.score_range().unwrap_or((0.0, 0.0));
    let max_len = t.iter().map(|x| x.actions.len()).max().unwrap_or(1).max(1);
    let cols = max_len.min(STRIP_W);
    let width = STRIP_X + STRIP_W as f64;
    let height = TOP + h * n as f64 + 2.0;
    let mut out = String::with_capacity(200 + n * 200);
    let _ = write!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" class="pool" width="{width}" height="{height}" viewBox="0 0 {width} {height}" data-trajectories="{n}" data-version="{}">"#,
        pool.version()
    );
    let _ = write!(
        out,
        r#"<text x="{SCORE_X}" y="12">score {lo} … {hi}</text><text x="{LEN_X}" y="12">length ≤ {max_len}</text><text x="{STRIP_X}" y="12">actions</text>"#
    );
    for (row, &i) in order.iter().enumerate() {
        let y = TOP + h * row as f64;
        let tr = &t[i];
        let frac = if hi > lo {
            (tr.score - lo) / (hi - lo)
        } else {
            1.0
        };
        let sw = 2.0 + frac * (SCORE_W - 2.0);
        let lw = (tr.actions.len() as f64 / max_len as f64 * LEN_W).max(1.0);
        let bh = (h - if h > 3.0 { 1.0 } else { 0.0 }).max(1.0);
        let _ = write!(
            out,
            r#"<rect class="score" x="{SCORE_X}" y="{y}" width="{sw:.1}" height="{bh}"><title>seq {} score {} length {}</title></rect><rect class="length" x="{LEN_X}" y="{y}" width="{lw:.1}" height="{bh}"/>"#,
            tr.seq,
            tr.score,
            tr.actions.len()
        );
        if let ActionSeq::Continuous { dim, data } = &tr.actions {
            sparklines(&mut out, data, *dim, y, bh, tr.actions.len(), max_len);
        }
    }
    if n > 0 && matches!(t[0].actions, ActionSeq::Discrete(_)) {
        let bmp = bitmap(pool, &order, cols, max_len);
        let _ = write!(
            out,
            r#"<image class="actions" x="{STRIP_X}" y="{TOP}" width="{STRIP_W}" height="{}" preserveAspectRatio="none" style="image-rendering:pixelated" href="data:image/bmp;base64,"#,
            h * n as f64
        );
        base64(&bmp, &mut out);
        out.push_str(r#""/>"#);
    }
    out.push_str("</svg>");
    out
}

/// One sparkline per dimension of a continuous trajectory, side by side in the strip,
/// each as wide as the trajectory is long relative to the longest.
fn sparklines(out: &mut String, data: &[f32], dim: usize, y: f64, h: f64, len: usize, max: usize) {
    if dim == 0 || len == 0 {
        return;
    }
    let lane = STRIP_W as f64 / dim as f64;
    let w = (lane - 6.0) * len as f64 / max as f64;
    let points = len.min(SPARK_POINTS);
    for d in 0..dim {
        let at = |k: usize| data[(k * len / points).min(len - 1) * dim + d];
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for k in 0..points {
            lo = lo.min(at(k));
            hi = hi.max(at(k));
        }
        let x0 = STRIP_X + lane * d as f64;
        let _ = write!(out, r#"<polyline class="d{}" points=""#, d % PALETTE.len());
        for k in 0..points {
            let fx = if points > 1 {
                k as f64 / (points - 1) as f64
            } else {
                0.5
            };
            let fy = if hi > lo {
                f64::from((at(k) - lo) / (hi - lo))
            } else {
                0.5
            };
            let _ = write!(out, "{:.1},{:.1} ", x0 + fx * w, y + h - fy * h);
        }
        out.push_str(r#""/>"#);
    }
}

/// An 8-bit palette BMP, top-down: a row per trajectory in `order`, `cols` pixels wide; a
/// trajectory of L actions fills the first `ceil(L / max_len * cols)` pixels, each the
/// colour of the first action it covers; the rest is the background.
fn bitmap(pool: &Pool, order: &[usize], cols: usize, max_len: usize) -> Vec<u8> {
    let rows = order.len();
    let stride = cols.div_ceil(4) * 4;
    let palette = (PALETTE.len() + 1) * 4;
    let offset = 14 + 40 + palette;
    let size = offset + stride * rows;
    let mut b = Vec::with_capacity(size);
    b.extend_from_slice(b"BM");
    b.extend_from_slice(&(size as u32).to_le_bytes());
    b.extend_from_slice(&0u32.to_le_bytes());
    b.extend_from_slice(&(offset as u32).to_le_bytes());
    b.extend_from_slice(&40u32.to_le_bytes());
    b.extend_from_slice(&(cols as i32).to_le_bytes());
    b.extend_from_slice(&(-(rows as i32)).to_le_bytes()); // negative: top-down
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(&8u16.to_le_bytes());
    b.extend_from_slice(&0u32.to_le_bytes()); // no compression
    b.extend_from_slice(&((stride * rows) as u32).to_le_bytes());
    b.extend_from_slice(&2835u32.to_le_bytes());
    b.extend_from_slice(&2835u32.to_le_bytes());
    b.extend_from_slice(&((PALETTE.len() + 1) as u32).to_le_bytes());
    b.extend_from_slice(&0u32.to_le_bytes());
    for [r, g, bl] in PALETTE {
        b.extend_from_slice(&[bl, g, r, 0]);
    }
    b.extend_from_slice(&[0xff, 0xff, 0xff, 0]); // the background, index 12
    let background = PALETTE.len() as u8;
    let t = pool.trajectories();
    for &i in order {
        let start = b.len();
        b.resize(start + stride, background);
        if let ActionSeq::Discrete(actions) = &t[i].actions {
            let len = actions.len();
            let filled = (len * cols).div_ceil(max_len).min(cols);
            for (x, px) in b[start..start + filled].iter_mut().enumerate() {
                let a = actions[(x * len / filled.max(1)).min(len - 1)];
                *px = (a as usize % PALETTE.len()) as u8;
            }
        }
    }
    b
}

/// Standard base64 (with padding) of `data`, appended to `out`.
fn base64(data: &[u8], out: &mut String) {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    out.reserve(data.len().div_ceil(3) * 4);
    for chunk in data.chunks(3) {
        let v = chunk
            .iter()
            .enumerate()
            .fold(0u32, |acc, (i, &x)| acc | u32::from(x) << (16 - 8 * i));
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ALPHABET[(v >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
}

#[cfg(test)]
mod tests;
