//! `floor`, `ceil` and `round` without the call into libm that `f64::floor`, `f64::ceil` and
//! `f64::round` compile to on baseline x86-64 (no SSE4.1 `roundsd`). A tick rounds a few hundred
//! times (the contact probes' trilinear reads, the erosion's voxel spans and decrements): the calls
//! were 9 % of its instructions before `floor` (`examples/tick_cost.rs` under callgrind). Each
//! equals its libm counterpart for every input, NaN and the infinities included, but for the sign
//! of a zero (−0.0 where libm gives it is +0.0 here). Callers compare, clamp or cast the result,
//! or subtract it from the input for a trilinear weight, which a zero weight skips or adds as
//! nothing: the two zeros give the same values, bit for bit.

/// 2^52: from there on every f64 is an integer (and casting to i64 would lose none below 2^63).
const INTEGRAL_FROM: f64 = 4_503_599_627_370_496.0;

/// `x.floor()`.
#[inline]
#[must_use]
pub fn floor(x: f64) -> f64 {
    if x.abs() < INTEGRAL_FROM {
        let t = x as i64 as f64; // towards zero, exactly
        if t > x {
            t - 1.0
        } else {
            t
        }
    } else {
        x // integral, infinite or NaN
    }
}

/// `x.ceil()`.
#[inline]
#[must_use]
pub fn ceil(x: f64) -> f64 {
    if x.abs() < INTEGRAL_FROM {
        let t = x as i64 as f64;
        if t < x {
            t + 1.0
        } else {
            t
        }
    } else {
        x
    }
}

/// `x.round()`: to the nearest integer, halves away from zero.
#[inline]
#[must_use]
pub fn round(x: f64) -> f64 {
    if x.abs() < INTEGRAL_FROM {
        let t = x as i64 as f64;
        let fraction = x - t; // exact: a fraction of a double is itself a double
        if fraction >= 0.5 {
            t + 1.0
        } else if fraction <= -0.5 {
            t - 1.0
        } else {
            t
        }
    } else {
        x
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // the same value, exactly, is the property tested
mod tests {
    use proptest::prelude::*;

    use super::{ceil, floor, round};

    /// The double `ulps` steps up (or down) from `x`, across zero too.
    fn ulps_from(x: f64, ulps: i64) -> f64 {
        fn up(y: f64) -> f64 {
            if y == 0.0 {
                f64::from_bits(1)
            } else if y > 0.0 {
                f64::from_bits(y.to_bits() + 1)
            } else {
                f64::from_bits(y.to_bits() - 1)
            }
        }
        (0..ulps.unsigned_abs()).fold(x, |y, _| if ulps > 0 { up(y) } else { -up(-y) })
    }

    /// Equal, or both NaN; zeros of either sign count as equal.
    fn same(a: f64, b: f64) -> bool {
        a == b || (a.is_nan() && b.is_nan())
    }

    #[test]
    fn each_is_libms_at_the_edges() {
        let below_half = 0.5 - f64::EPSILON / 4.0; // the largest double under 0.5
        let halves = [0.5, 1.5, 2.5, -0.5, -1.5, -2.5, below_half, -below_half];
        let edges = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            7.999_999_999_999_999,
            -7.999_999_999_999_999,
            2.0f64.powi(52) - 0.5,
            -2.0f64.powi(52) + 0.5,
            2.0f64.powi(52) + 1.0,
            -2.0f64.powi(52) - 2.0,
            2.0f64.powi(60),
            -1e300,
            1e300,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            f64::EPSILON,
            f64::MAX,
            f64::MIN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for x in halves.into_iter().chain(edges) {
            assert!(same(floor(x), x.floor()), "floor {x}");
            assert!(same(ceil(x), x.ceil()), "ceil {x}");
            assert!(same(round(x), x.round()), "round {x}");
            // What callers do with them: the same index, the same decrement.
            assert_eq!(ceil(x) as u64, x.ceil() as u64, "ceil as u64 {x}");
            assert_eq!(round(x) as usize, x.round() as usize, "round as usize {x}");
        }
        // The one difference: the sign of a zero.
        assert_eq!(floor(-0.0).to_bits(), 0.0f64.to_bits());
        assert_eq!(ceil(-0.5).to_bits(), 0.0f64.to_bits());
        assert_eq!(round(-0.25).to_bits(), 0.0f64.to_bits());
    }

    proptest! {
        #[test]
        fn each_is_libms_for_any_value(x in proptest::num::f64::ANY) {
            prop_assert!(same(floor(x), x.floor()), "floor {}", x);
            prop_assert!(same(ceil(x), x.ceil()), "ceil {}", x);
            prop_assert!(same(round(x), x.round()), "round {}", x);
        }

        #[test]
        fn each_is_libms_over_index_coordinates(x in -1.0e4f64..1.0e4) {
            prop_assert_eq!(floor(x), x.floor());
            prop_assert!(same(ceil(x), x.ceil()));
            prop_assert!(same(round(x), x.round()));
        }

        #[test]
        fn each_is_libms_near_halves_and_integers(n in -100_000i64..100_000, ulps in -4i64..=4, half in any::<bool>()) {
            let base = n as f64 + if half { 0.5 } else { 0.0 };
            let x = ulps_from(base, ulps);
            prop_assert!(same(floor(x), x.floor()), "floor {}", x);
            prop_assert!(same(ceil(x), x.ceil()), "ceil {}", x);
            prop_assert!(same(round(x), x.round()), "round {}", x);
        }
    }
}
