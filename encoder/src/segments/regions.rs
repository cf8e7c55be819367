//! Region mask profiles (module doc, "Region mask profiles"): each component's masks summed
//! per view, and the disagreement of two components' profiles that may veto their join.

use rayon::prelude::*;
use slag_common::mask_record::MaskRecord;

/// Most entries of one region's mask profile ([`Regions`]); beyond it the lightest go.
pub(super) const PROFILE_CAP: usize = 64;

/// Each component's *mask profile* (module doc, "Region mask profiles"): the record's
/// `(view, mask, a_kj)` entries of its Gaussians, summed per `(view, mask)`, sorted by
/// `(view, mask)`, at most [`PROFILE_CAP`] entries (the heaviest; ties to the smaller key).
/// Indexed by union-find root; a non-root's profile is empty.
pub(super) struct Regions {
    profiles: Vec<Vec<(u16, u16, f32)>>,
    veto: f32,
}

impl Regions {
    /// Every Gaussian its own region, with its recorded slots.
    pub(super) fn new(record: &MaskRecord, veto: f32) -> Self {
        let profiles = (0..record.len())
            .into_par_iter()
            .map(|i| {
                let mut p: Vec<(u16, u16, f32)> =
                    record.of(i).map(|s| (s.view, s.mask, s.weight)).collect();
                p.sort_by_key(|e| (e.0, e.1));
                p
            })
            .collect();
        Regions { profiles, veto }
    }

    /// Whether the regions of roots `a` and `b` may join: unless their disagreement exceeds
    /// the veto (no shared view: they may).
    pub(super) fn allows(&self, a: u32, b: u32) -> bool {
        self.veto >= 1.0
            || region_disagreement(&self.profiles[a as usize], &self.profiles[b as usize])
                .is_none_or(|d| d <= self.veto)
    }

    /// Root `into` took root `from` in: its profile is the sum of both.
    pub(super) fn absorb(&mut self, into: u32, from: u32) {
        let b = std::mem::take(&mut self.profiles[from as usize]);
        let a = std::mem::take(&mut self.profiles[into as usize]);
        self.profiles[into as usize] = merge_profiles(&a, &b);
    }
}

/// The sum of two profiles (sorted by `(view, mask)`), cut to the [`PROFILE_CAP`] heaviest.
pub(super) fn merge_profiles(a: &[(u16, u16, f32)], b: &[(u16, u16, f32)]) -> Vec<(u16, u16, f32)> {
    let mut out: Vec<(u16, u16, f32)> = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        let take_a = j >= b.len() || (i < a.len() && (a[i].0, a[i].1) <= (b[j].0, b[j].1));
        let e = if take_a {
            i += 1;
            a[i - 1]
        } else {
            j += 1;
            b[j - 1]
        };
        match out.last_mut() {
            Some(l) if (l.0, l.1) == (e.0, e.1) => l.2 += e.2,
            _ => out.push(e),
        }
    }
    if out.len() > PROFILE_CAP {
        out.sort_by(|x, y| y.2.total_cmp(&x.2).then((x.0, x.1).cmp(&(y.0, y.1))));
        out.truncate(PROFILE_CAP);
        out.sort_by_key(|e| (e.0, e.1));
    }
    out
}

/// The mask disagreement of two regions' profiles, in `[0, 1]`: over the views both hold, one
/// minus the overlap `Σ_m min(p_a(m | v), p_b(m | v))` of their mask distributions, each view
/// counting `min(W_a(v), W_b(v))` (its total weight in either). `None` without a shared view.
pub(super) fn region_disagreement(a: &[(u16, u16, f32)], b: &[(u16, u16, f32)]) -> Option<f32> {
    let view_total = |p: &[(u16, u16, f32)], from: usize| -> (u16, f32, usize) {
        let v = p[from].0;
        let mut k = from;
        let mut t = 0.0;
        while k < p.len() && p[k].0 == v {
            t += p[k].2;
            k += 1;
        }
        (v, t, k)
    };
    let (mut i, mut j) = (0, 0);
    let (mut agree, mut total) = (0.0f32, 0.0f32);
    while i < a.len() && j < b.len() {
        let (va, ta, ea) = view_total(a, i);
        let (vb, tb, eb) = view_total(b, j);
        if va < vb {
            i = ea;
            continue;
        }
        if vb < va {
            j = eb;
            continue;
        }
        if ta > 0.0 && tb > 0.0 {
            let mut overlap = 0.0f32;
            let (mut x, mut y) = (i, j);
            while x < ea && y < eb {
                match a[x].1.cmp(&b[y].1) {
                    std::cmp::Ordering::Less => x += 1,
                    std::cmp::Ordering::Greater => y += 1,
                    std::cmp::Ordering::Equal => {
                        overlap += (a[x].2 / ta).min(b[y].2 / tb);
                        x += 1;
                        y += 1;
                    }
                }
            }
            let w = ta.min(tb);
            agree += w * overlap.min(1.0);
            total += w;
        }
        i = ea;
        j = eb;
    }
    (total > 0.0 && total.is_finite()).then(|| (1.0 - agree / total).clamp(0.0, 1.0))
}
