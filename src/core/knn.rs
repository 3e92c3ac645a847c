//! The kNN reward r(t) of SPEC §3, given the distances of the current prefix to every
//! stored trajectory.

/// r(t) = exp(f(t)) − exp(0.5).
pub fn reward_from_f(f: f64) -> f64 {
    f.exp() - 0.5f64.exp()
}

/// Reusable buffers for [`knn_f`], so a step allocates nothing.
#[derive(Debug, Default, Clone)]
pub struct KnnScratch {
    p: Vec<f64>,
    /// Per entry: P in the high half, the entry's (x, seq) rank in the low half, so that
    /// the order of the keys is the order that picks K.
    keys: Vec<u128>,
    /// A copy of `keys` for the selection.
    sel: Vec<u128>,
    /// Per entry: 1 if it is in K, else 0.
    pick: Vec<i32>,
    /// The `xs` and `seqs` (as bits) that `rank` was computed for.
    rank_xs: Vec<u64>,
    rank_seqs: Vec<u64>,
    /// Per entry: `u64::MAX` minus its place in the order (x descending, seq ascending).
    rank: Vec<u64>,
    idx: Vec<usize>,
    /// [`knn_f_discrete`]: the members of K in pool order.
    members: Vec<u32>,
    /// [`knn_f_discrete`]: a copy of `ms` for the selection.
    sel_m: Vec<u32>,
    /// [`knn_f_discrete`]: entries per m − min m.
    hist: Hist,
    /// [`knn_f_discrete`]: `inv[m]` = 1 / (2m), as `1.0 / d` computes it.
    inv: Vec<f64>,
}

/// The counting buffer of [`knn_f_discrete`]: ranges of m up to its length are counted.
#[derive(Debug, Clone)]
struct Hist(Box<[u32; 256]>);

impl Default for Hist {
    fn default() -> Hist {
        Hist(Box::new([0; 256]))
    }
}

impl std::ops::Deref for Hist {
    type Target = [u32];
    fn deref(&self) -> &[u32] {
        &self.0[..]
    }
}

impl std::ops::DerefMut for Hist {
    fn deref_mut(&mut self) -> &mut [u32] {
        &mut self.0[..]
    }
}

/// An integer with the order of [`f64::total_cmp`].
#[inline]
fn total_order_key(x: f64) -> u64 {
    let bits = x.to_bits() as i64;
    let flipped = bits ^ ((((bits >> 63) as u64) >> 1) as i64);
    (flipped as u64) ^ (1 << 63)
}

impl KnnScratch {
    /// Ranks the entries by x descending, then seq ascending: the order that breaks ties
    /// in P. It depends on the pool only, so it is kept until `xs` or `seqs` change.
    fn rank_for(&mut self, xs: &[f64], seqs: &[u64]) {
        let same = self.rank.len() == xs.len()
            && self.rank_seqs.as_slice() == seqs
            && self.rank_xs.iter().zip(xs).all(|(&a, &b)| a == b.to_bits());
        if same {
            return;
        }
        let idx = &mut self.idx;
        idx.clear();
        idx.extend(0..xs.len());
        idx.sort_unstable_by(|&a, &b| xs[b].total_cmp(&xs[a]).then_with(|| seqs[a].cmp(&seqs[b])));
        self.rank.clear();
        self.rank.resize(xs.len(), 0);
        for (place, &i) in idx.iter().enumerate() {
            self.rank[i] = u64::MAX - place as u64;
        }
        self.rank_xs.clear();
        self.rank_xs.extend(xs.iter().map(|x| x.to_bits()));
        self.rank_seqs.clear();
        self.rank_seqs.extend_from_slice(seqs);
    }
}

/// f(t) = Σ_{i∈K} x_i·P_i for distances `dis`, normalised scores `xs` (in [0, 1]) and
/// seqs `seqs` (all aligned, non-empty), with K the first `k` entries ordered by P descending, then x
/// descending, then seq ascending. P is not renormalised over K.
///
/// The sum runs over K in ascending seq (= pool) order, so the result is reproducible bit
/// for bit. Cost: O(|D|) plus selecting the top k (one selection on integer keys; the
/// (x, seq) order that breaks ties in P is computed once per pool).
pub fn knn_f(dis: &[f64], xs: &[f64], seqs: &[u64], k: usize, scratch: &mut KnnScratch) -> f64 {
    let n = dis.len();
    debug_assert!(n > 0 && xs.len() == n && seqs.len() == n);
    let p = &mut scratch.p;
    p.clear();
    let exact = dis.iter().filter(|&&d| d == 0.0).count();
    if exact > 0 {
        // Exact prefix matches share the probability mass (the limit dis → 0).
        let share = 1.0 / exact as f64;
        p.extend(dis.iter().map(|&d| if d == 0.0 { share } else { 0.0 }));
    } else {
        p.extend(dis.iter().map(|&d| 1.0 / d));
        let total: f64 = p.iter().sum();
        p.iter_mut().for_each(|q| *q /= total);
    }
    if k >= n {
        return p.iter().zip(xs).map(|(&pi, &xi)| xi * pi).sum();
    }
    // K is the k largest keys (all distinct): those at or above the k-th largest.
    scratch.rank_for(xs, seqs);
    let keys = &mut scratch.keys;
    keys.clear();
    keys.extend(
        scratch
            .p
            .iter()
            .zip(&scratch.rank)
            .map(|(&pi, &r)| (u128::from(total_order_key(pi)) << 64) | u128::from(r)),
    );
    let sel = &mut scratch.sel;
    sel.clear();
    sel.extend_from_slice(keys);
    let (_, &mut threshold, _) = sel.select_nth_unstable(n - k);
    scratch.pick.clear();
    scratch
        .pick
        .extend(keys.iter().map(|&key| i32::from(key >= threshold)));
    // Σ over K in pool order. Entries outside K add (x·P)·0 = +0.0, which changes no
    // partial sum: every term is ≥ +0.0 (x and P are), so the sum never is −0.0 after
    // its first term. No branch depends on membership.
    let p = &scratch.p;
    p.iter()
        .zip(xs)
        .zip(scratch.pick.iter())
        .map(|((&pi, &xi), &m)| (xi * pi) * f64::from(m))
        .sum()
}

/// How many counting passes [`kth_from_hint`] and [`kth_masks_from_hint`] try before
/// they give up on a remembered k-th smallest count.
const HINT_STEPS: u32 = 3;

/// The number of counts below `v`.
#[inline]
fn count_below(ms: &[u32], v: u32) -> usize {
    ms.iter().fold(0u32, |c, &m| c + u32::from(m < v)) as usize
}

/// The counts that satisfy `pred`, as a bit set over their indices (`ms.len()` ≤ 64).
/// In chunks of eight, which the compiler turns into vector compares.
#[inline(always)]
fn mask_where(ms: &[u32], pred: impl Fn(u32) -> bool) -> u64 {
    let mut mask = 0u64;
    let mut chunks = ms.chunks_exact(8);
    for (c, chunk) in (&mut chunks).enumerate() {
        let mut bits = 0u64;
        for (j, &m) in chunk.iter().enumerate() {
            bits |= u64::from(pred(m)) << j;
        }
        mask |= bits << (8 * c);
    }
    let base = ms.len() - chunks.remainder().len();
    for (j, &m) in chunks.remainder().iter().enumerate() {
        mask |= u64::from(pred(m)) << (base + j);
    }
    mask
}

/// 1/(2m), as `1.0 / d` computes it for d = 2m: from the table when it reaches m.
#[inline(always)]
fn inv_of(inv: &[f64], m: u32) -> f64 {
    match inv.get(m as usize) {
        Some(&v) => v,
        None => 1.0 / (2.0 * f64::from(m)),
    }
}

/// Extends the table of 1/(2m) to cover m < `need` (with room to grow).
fn cover(inv: &mut Vec<f64>, need: usize) {
    if inv.len() < need {
        let from = inv.len();
        inv.extend((from..need.max(2 * from)).map(|m| 1.0 / (2.0 * m as f64)));
    }
}

/// The k-th smallest of `ms` (m*) and how many counts lie below it, searched upward from
/// `start` when that is a lower bound on m*: `None` if it is not (more than k − 1 counts
/// below it), or if m* is more than [`HINT_STEPS`] − 1 above it.
///
/// One episode's counts only grow (by 0 or 1 per step), so the k-th smallest of a step is
/// at least the previous step's, and usually equal to it or one more: one or two
/// counting passes instead of a histogram. The check makes a stale `start` harmless.
fn kth_from_hint(ms: &[u32], k: usize, start: u32) -> Option<(u32, usize)> {
    let mut below = count_below(ms, start);
    if below >= k {
        return None;
    }
    let mut at = start;
    for _ in 0..HINT_STEPS {
        let next = at.checked_add(1)?;
        let upto = count_below(ms, next);
        if upto >= k {
            return Some((at, below));
        }
        below = upto;
        at = next;
    }
    None
}

/// K's boundary as bit sets (`ms.len()` ≤ 64): m*, the counts below it, those at it,
/// and how many lie below. See [`kth_from_hint`]: the same search, one bit set per pass.
fn kth_masks_from_hint(ms: &[u32], k: usize, start: u32) -> Option<(u32, u64, u64, usize)> {
    let mut below = mask_where(ms, |m| m < start);
    let mut count = below.count_ones() as usize;
    if count >= k {
        return None;
    }
    let mut value = start;
    for _ in 0..HINT_STEPS {
        let at = mask_where(ms, |m| m == value);
        let here = at.count_ones() as usize;
        if count + here >= k {
            return Some((value, below, at, count));
        }
        below |= at;
        count += here;
        value = value.checked_add(1)?;
    }
    None
}

/// [`knn_f`] for discrete distances dis_i = 2·`ms[i]` (`ms` the mismatch counts), with
/// `by_place` the entries in the order x descending, then seq ascending and `place_of`
/// its inverse ([`crate::core::Pool`] keeps both): exactly `knn_f(2·ms, xs, seqs, k)`,
/// bit for bit. `kth` is the k-th smallest count of this episode's previous call (or
/// `None`); it is updated to this call's, and only speeds up finding it.
///
/// Why the same K: for distinct even integers d < d' < 2^33, 1/d and 1/d' differ by a
/// factor ≥ 1 + 2^-32, far above rounding, so P = (1/d)/Σ orders entries exactly as d
/// does, and equal d give equal P. With exact matches, P is `share` for d = 0 and 0
/// otherwise: ordering by d picks the same d = 0 entries (ties by place), and the P = 0
/// entries of K add +0.0 whichever they are. So K is the first `k` entries by
/// (m ascending, place ascending): every entry below the k-th smallest m (m*), plus the
/// first of those at m* in place order. m* is found from the previous step's (see
/// [`kth_from_hint`]), else by counting over the (small) range of m.
/// 1/d comes from a table (the bits of `1.0 / d`); the total sums the same terms in the
/// same order as `knn_f`; only the k members of K are divided by it and summed (in pool
/// order; the +0.0 terms `knn_f` adds for the others change nothing, see below).
pub(crate) fn knn_f_discrete(
    ms: &[u32],
    xs: &[f64],
    by_place: &[u32],
    place_of: &[u32],
    k: usize,
    scratch: &mut KnnScratch,
    kth: &mut Option<u32>,
) -> f64 {
    let n = ms.len();
    debug_assert!(n > 0 && xs.len() == n && by_place.len() == n && place_of.len() == n && k > 0);
    // P_i = num(m_i) / den: share = 1/exact for m = 0 with exact matches, else 1/d / Σ.
    let exact = ms.iter().fold(0u32, |c, &m| c + u32::from(m == 0));
    let (den, share) = if exact > 0 {
        (1.0, 1.0 / f64::from(exact))
    } else {
        let inv = &scratch.inv;
        let total: f64 = ms.iter().map(|&m| inv_of(inv, m)).sum();
        (total, 0.0)
    };
    // The numerator of P for a count: no branch on the count.
    let num = |inv: &[f64], m: u32| -> f64 {
        if exact > 0 {
            f64::from_bits(share.to_bits() & 0u64.wrapping_sub(u64::from(m == 0)))
        } else {
            inv_of(inv, m)
        }
    };
    if k >= n {
        let inv = &scratch.inv;
        return ms
            .iter()
            .zip(xs)
            .map(|(&m, &xi)| xi * (num(inv, m) / den))
            .sum();
    }
    // Σ over K in pool order, dividing only the k members by the total. `knn_f` also
    // adds (x·P)·0 = +0.0 for every other entry (x ≥ +0.0 and P ≥ +0.0), which changes
    // no partial sum but an initial −0.0 into +0.0, and −0.0 + t = +0.0 + t for the
    // first member's t ≥ +0.0: the same sum.
    if n <= 64 {
        let (threshold, below, at, count) = match kth.and_then(|h| kth_masks_from_hint(ms, k, h)) {
            Some(found) => found,
            None => {
                let (threshold, count) = kth_by_counting(ms, k, scratch);
                let below = mask_where(ms, |m| m < threshold);
                let at = mask_where(ms, |m| m == threshold);
                (threshold, below, at, count)
            }
        };
        *kth = Some(threshold);
        cover(&mut scratch.inv, threshold as usize + 64);
        let members = members_mask(below, at, k - count, by_place, place_of);
        let inv = &scratch.inv;
        let mut rest = members;
        return std::iter::from_fn(|| {
            (rest != 0).then(|| {
                let i = rest.trailing_zeros() as usize;
                rest &= rest - 1;
                i
            })
        })
        .map(|i| xs[i] * (num(inv, ms[i]) / den))
        .sum();
    }
    let (threshold, below) = match kth.and_then(|h| kth_from_hint(ms, k, h)) {
        Some(found) => found,
        None => kth_by_counting(ms, k, scratch),
    };
    *kth = Some(threshold);
    cover(&mut scratch.inv, threshold as usize + 64);
    let pick = &mut scratch.pick;
    pick.clear();
    pick.extend(ms.iter().map(|&m| i32::from(m < threshold)));
    // Of the entries at m*, the k − below first in place order (no branch on m).
    let mut need = k - below;
    for &i in by_place {
        let i = i as usize;
        let take = (ms[i] == threshold) & (need > 0);
        pick[i] |= i32::from(take);
        need -= usize::from(take);
    }
    // The members, in pool order, by a branch-free compaction.
    let members = &mut scratch.members;
    members.clear();
    members.resize(n, 0);
    let mut c = 0;
    for (i, &picked) in pick.iter().enumerate() {
        members[c] = i as u32;
        c += usize::from(picked != 0);
    }
    let inv = &scratch.inv;
    members[..c]
        .iter()
        .map(|&i| xs[i as usize] * (num(inv, ms[i as usize]) / den))
        .sum()
}

/// The k-th smallest of `ms` and how many lie below it: by counting when the range of
/// the counts is small (distances of one episode move together), else by selection.
fn kth_by_counting(ms: &[u32], k: usize, scratch: &mut KnnScratch) -> (u32, usize) {
    let (min_m, max_m) = ms
        .iter()
        .fold((u32::MAX, 0u32), |(lo, hi), &m| (lo.min(m), hi.max(m)));
    cover(&mut scratch.inv, max_m as usize + 1);
    let range = (max_m - min_m) as usize + 1;
    if range <= scratch.hist.len() {
        let hist = &mut scratch.hist[..range];
        hist.fill(0);
        for &m in ms {
            hist[(m - min_m) as usize] += 1;
        }
        let mut below = 0usize;
        let mut at = 0usize;
        while below + (hist[at] as usize) < k {
            below += hist[at] as usize;
            at += 1;
        }
        (min_m + at as u32, below)
    } else {
        let sel = &mut scratch.sel_m;
        sel.clear();
        sel.extend_from_slice(ms);
        let (_, &mut threshold, _) = sel.select_nth_unstable(k - 1);
        (threshold, count_below(ms, threshold))
    }
}

/// K as a bit set over pool indices (at most 64): every entry of `below` (those below
/// m*), and the first `need` (≥ 1) of `at` (those at m*) in place order.
fn members_mask(below: u64, mut at: u64, need: usize, by_place: &[u32], place_of: &[u32]) -> u64 {
    if at.count_ones() as usize == need {
        return below | at;
    }
    // The places of the entries at m*, the `need` lowest of them, back to pool indices.
    let mut places = 0u64;
    while at != 0 {
        let i = at.trailing_zeros() as usize;
        at &= at - 1;
        places |= 1 << place_of[i];
    }
    let mut members = below;
    for _ in 0..need {
        let p = places.trailing_zeros() as usize;
        places &= places.wrapping_sub(1);
        members |= 1 << by_place[p];
    }
    members
}

#[cfg(test)]
mod tests;
