//! The kept pairs of one Gaussian's mixture: the rule by which a full set of `(a, atom)` slots
//! takes a new pair. The mixture's reduction ([`super::mixture`]) and the streamed fold
//! ([`super::fold`]) both keep pairs by it, so that they keep the same pairs, bit for bit.

/// Offers `(a_kj, atom)` to `slots`, every one of them in use: the weakest slot (least `a`; of
/// equal `a`, the larger atom) is replaced when the offered pair is stronger (larger `a`; of
/// equal `a`, the lower atom). Nothing changes otherwise, nor when `slots` is empty.
pub(crate) fn replace_weakest(slots: &mut [(f32, u32)], a: f32, atom: u32) {
    let weakest = slots
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.0.total_cmp(&y.1.0).then(y.1.1.cmp(&x.1.1)));
    if let Some((i, &(wa, watom))) = weakest
        && (a > wa || (a == wa && atom < watom))
    {
        slots[i] = (a, atom);
    }
}

#[cfg(test)]
mod tests {
    use super::replace_weakest;

    #[test]
    fn the_weakest_slot_gives_way_to_a_stronger_pair_only() {
        let mut slots = [(0.5, 3), (0.2, 7), (0.2, 4), (0.9, 1)];
        // Weaker than the weakest (0.2, 7): no change.
        replace_weakest(&mut slots, 0.1, 0);
        assert_eq!(slots, [(0.5, 3), (0.2, 7), (0.2, 4), (0.9, 1)]);
        // Equal a, larger atom than the weakest: no change.
        replace_weakest(&mut slots, 0.2, 8);
        assert_eq!(slots, [(0.5, 3), (0.2, 7), (0.2, 4), (0.9, 1)]);
        // Equal a, lower atom: replaces the weakest of the ties, the larger atom 7.
        replace_weakest(&mut slots, 0.2, 5);
        assert_eq!(slots, [(0.5, 3), (0.2, 5), (0.2, 4), (0.9, 1)]);
        // Stronger: replaces the weakest, now (0.2, 5).
        replace_weakest(&mut slots, 0.6, 9);
        assert_eq!(slots, [(0.5, 3), (0.6, 9), (0.2, 4), (0.9, 1)]);
        let mut none: [(f32, u32); 0] = [];
        replace_weakest(&mut none, 1.0, 0);
    }
}
