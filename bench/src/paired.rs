//! The paired comparison of two models on the same images: which images only one of them gets
//! right, and McNemar's statistic of the change.

/// Images only the first model gets right (`lost`) and only the second (`gained`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Paired {
    pub lost: usize,
    pub gained: usize,
}

impl Paired {
    /// Pairs per-image right/wrong flags of the first and the second model (same image order).
    pub fn new(first: &[bool], second: &[bool]) -> Self {
        let count = |f: fn(bool, bool) -> bool| first.iter().zip(second).filter(|&(&a, &b)| f(a, b)).count();
        Paired { lost: count(|a, b| a && !b), gained: count(|a, b| !a && b) }
    }

    /// McNemar's statistic `(gained − lost)/√(gained + lost)` (0 when no image changed).
    pub fn z(&self) -> f64 {
        let n = (self.gained + self.lost) as f64;
        if n == 0.0 { 0.0 } else { (self.gained as f64 - self.lost as f64) / n.sqrt() }
    }

    /// Beyond ±1.96 the change is unlikely to be noise of the images (two-sided 5%).
    pub fn significant(&self) -> bool {
        self.z().abs() >= 1.96
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_changed_images_and_their_statistic() {
        let first = [true, true, false, false, true];
        let second = [true, false, true, true, true];
        let p = Paired::new(&first, &second);
        assert_eq!(p, Paired { lost: 1, gained: 2 });
        assert!((p.z() - 1.0 / 3f64.sqrt()).abs() < 1e-12);
        assert!(!p.significant());
        let nine = Paired { lost: 0, gained: 4 };
        assert!(nine.significant(), "4 gained, none lost: z = 2");
        assert_eq!(Paired::new(&first, &first).z(), 0.0);
    }
}
