//! Small dense-vector helpers shared by the solver and the fusion window: dot products and the
//! infinity norm. Two dot products on purpose: [`dot`] sums in order (the iteration loop's model
//! decreases and step norms, where the exact value must not depend on the vector's length modulo
//! four), [`dot_interleaved`] keeps four partial sums (the factorisations' inner products, hot
//! loops where a single running sum is a chain of dependent additions).

/// `Σ aᵢ bᵢ`, summed in order.
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// `Σ aᵢ bᵢ` over the common length, in four interleaved partial sums so that the compiler can
/// keep them in one vector register. The products in the factorisations are short (a row
/// reaches a few blocks back), hence four and not more.
#[inline(always)]
pub fn dot_interleaved(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 4];
    let mut chunks_a = a.chunks_exact(4);
    let mut chunks_b = b.chunks_exact(4);
    for (x, y) in (&mut chunks_a).zip(&mut chunks_b) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut tail = 0.0;
    for (x, y) in chunks_a.remainder().iter().zip(chunks_b.remainder()) {
        tail += x * y;
    }
    (acc[0] + acc[2]) + (acc[1] + acc[3]) + tail
}

/// `max |vᵢ|` (0 for an empty vector).
pub fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_dot_products_agree_on_every_tail_length() {
        for n in 0..11 {
            let a: Vec<f64> = (0..n).map(|i| 0.5 + i as f64).collect();
            let b: Vec<f64> = (0..n).map(|i| 2.0 - i as f64 * 0.25).collect();
            assert!(
                (dot(&a, &b) - dot_interleaved(&a, &b)).abs() < 1e-12,
                "n = {n}"
            );
        }
        assert_eq!(dot_interleaved(&[1.0, 2.0, 3.0], &[1.0]), 1.0);
        assert_eq!(max_abs(&[1.0, -3.0, 2.0]), 3.0);
        assert_eq!(max_abs(&[]), 0.0);
    }
}
