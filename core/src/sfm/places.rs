//! Place recognition: which images see the same place when a drifted prior puts the two passes of a
//! revisit metres apart, so that neither its frustum test ([`super::pairs`]) nor its epipolar gate
//! ([`super::matching`]) would pair them. Each image gets one global descriptor, VLAD (Jégou et al.
//! 2010, with the intra-normalisation of Arandjelović & Zisserman 2013): every local SIFT descriptor's
//! residual to its nearest visual word, summed per word; each word's sum normalised to unit length (so a
//! burst of one repeated texture counts once, not once per window); a signed square root; unit length
//! overall. Two images' similarity is the dot product. The vocabulary is k-means'd on the mission's own
//! descriptors (no pretrained model to ship, and the words fit the place). The retrieved pairs are only
//! candidates: [`super::loops`] verifies each geometrically.

use rayon::prelude::*;

use super::matching::dot128;

const D: usize = 128;

/// Vocabulary and retrieval settings.
#[derive(Clone, Debug)]
pub struct PlaceOptions {
    /// Visual words (the VLAD vector has `words × 128` entries).
    pub words: usize,
    /// Descriptors the vocabulary is clustered from (taken evenly across the images).
    pub vocabulary_sample: usize,
    /// Lloyd iterations of the k-means.
    pub iterations: usize,
    /// Retrieved neighbours per image.
    pub top_k: usize,
}

impl Default for PlaceOptions {
    fn default() -> Self {
        PlaceOptions {
            words: 32,
            vocabulary_sample: 40_000,
            iterations: 10,
            top_k: 4,
        }
    }
}

/// The visual words: `words × 128` floats, each row a cluster centre of unit SIFT descriptors.
#[derive(Clone, Debug)]
pub struct Vocabulary {
    words: Vec<f32>,
}

impl Vocabulary {
    /// k-means over an even sample of `images`' descriptors (each 128 floats back to back). `None` with
    /// fewer descriptors than words. Deterministic: the seeds are evenly spaced sample members.
    pub fn train(images: &[&[f32]], opts: &PlaceOptions) -> Option<Vocabulary> {
        let total: usize = images.iter().map(|d| d.len() / D).sum();
        let k = opts.words.max(1);
        if total < k {
            return None;
        }
        let stride = total.div_ceil(opts.vocabulary_sample.max(k));
        let sample: Vec<&[f32]> = images
            .iter()
            .flat_map(|d| d.chunks_exact(D))
            .step_by(stride)
            .collect();
        let mut words: Vec<f32> = (0..k)
            .flat_map(|w| sample[w * sample.len() / k].iter().copied())
            .collect();
        for _ in 0..opts.iterations {
            let voc = Vocabulary {
                words: words.clone(),
            };
            let assign: Vec<usize> = sample.par_iter().map(|d| voc.nearest(d)).collect();
            let mut sums = vec![0.0f64; k * D];
            let mut counts = vec![0usize; k];
            for (d, &w) in sample.iter().zip(&assign) {
                counts[w] += 1;
                for (s, &x) in sums[w * D..(w + 1) * D].iter_mut().zip(d.iter()) {
                    *s += x as f64;
                }
            }
            for w in 0..k {
                // An empty cluster keeps its centre (it is a sample member, so it can win again).
                if counts[w] > 0 {
                    for (c, s) in words[w * D..(w + 1) * D]
                        .iter_mut()
                        .zip(&sums[w * D..(w + 1) * D])
                    {
                        *c = (*s / counts[w] as f64) as f32;
                    }
                }
            }
        }
        Some(Vocabulary { words })
    }

    pub fn len(&self) -> usize {
        self.words.len() / D
    }

    pub fn is_empty(&self) -> bool {
        self.words.is_empty()
    }

    /// The word nearest descriptor `d` (L2; the words are not unit length, so not by dot product alone).
    pub fn nearest(&self, d: &[f32]) -> usize {
        let mut best = (f32::INFINITY, 0);
        for (w, c) in self.words.chunks_exact(D).enumerate() {
            // ‖d − c‖² − ‖d‖² = ‖c‖² − 2 d·c.
            let score = dot128(c, c) - 2.0 * dot128(d, c);
            if score < best.0 {
                best = (score, w);
            }
        }
        best.1
    }

    /// The VLAD vector of one image's descriptors (`len() × 128`, unit length; all zeros for none).
    pub fn vlad(&self, descriptors: &[f32]) -> Vec<f32> {
        let k = self.len();
        let mut v = vec![0.0f32; k * D];
        for d in descriptors.chunks_exact(D) {
            let w = self.nearest(d);
            let c = &self.words[w * D..(w + 1) * D];
            for ((o, &x), &m) in v[w * D..(w + 1) * D].iter_mut().zip(d).zip(c) {
                *o += x - m;
            }
        }
        for block in v.chunks_exact_mut(D) {
            let n = dot128(block, block).sqrt();
            if n > 0.0 {
                block.iter_mut().for_each(|x| *x /= n);
            }
        }
        for x in v.iter_mut() {
            *x = x.signum() * x.abs().sqrt();
        }
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if n > 0.0 {
            v.iter_mut().for_each(|x| *x /= n);
        }
        v
    }
}

/// Dot product of two VLAD vectors (multiples of 128 long).
fn similarity(a: &[f32], b: &[f32]) -> f32 {
    a.chunks_exact(D)
        .zip(b.chunks_exact(D))
        .map(|(x, y)| dot128(x, y))
        .sum()
}

/// For each image, its `top_k` most similar images among those `eligible(i, j)` allows, as pairs
/// `(i, j, similarity)` with `i < j`, each pair once (at its higher similarity, which is symmetric), sorted
/// by (i, j). O(n²) dot products of `vlads`' length: 3,081 images of 32 words take a few seconds.
pub fn retrieve(
    vlads: &[Vec<f32>],
    eligible: &(dyn Fn(usize, usize) -> bool + Sync),
    top_k: usize,
) -> Vec<(usize, usize, f32)> {
    let n = vlads.len();
    let mut pairs: Vec<(usize, usize, f32)> = (0..n)
        .into_par_iter()
        .flat_map_iter(|i| {
            let mut best: Vec<(f32, usize)> = (0..n)
                .filter(|&j| j != i && eligible(i, j))
                .map(|j| (similarity(&vlads[i], &vlads[j]), j))
                .collect();
            best.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            best.truncate(top_k);
            best.into_iter().map(move |(s, j)| (i.min(j), i.max(j), s))
        })
        .collect();
    pairs.sort_by_key(|p| (p.0, p.1));
    pairs.dedup_by(|a, b| (a.0, a.1) == (b.0, b.1));
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn unit(rng: &mut impl Rng) -> Vec<f32> {
        let v: Vec<f32> = (0..D).map(|_| rng.random::<f32>() - 0.5).collect();
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.into_iter().map(|x| x / n).collect()
    }

    fn noisy(d: &[f32], sigma: f32, rng: &mut impl Rng) -> Vec<f32> {
        let v: Vec<f32> = d
            .iter()
            .map(|x| x + sigma * (rng.random::<f32>() - 0.5))
            .collect();
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.into_iter().map(|x| x / n).collect()
    }

    /// Ten places, each a set of 150 landmark descriptors; two views of each place see 70 % of its
    /// landmarks with descriptor noise, plus clutter of their own, and share a background of common
    /// descriptors with every other view (the street's repeated texture). Every view's best match must be
    /// the other view of its place.
    #[test]
    fn two_views_of_a_place_retrieve_each_other_over_other_places() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let common: Vec<Vec<f32>> = (0..40).map(|_| unit(&mut rng)).collect();
        let places: Vec<Vec<Vec<f32>>> = (0..10)
            .map(|_| (0..150).map(|_| unit(&mut rng)).collect())
            .collect();
        let mut images: Vec<Vec<f32>> = Vec::new();
        for place in &places {
            for _ in 0..2 {
                let mut d = Vec::new();
                for l in place {
                    if rng.random::<f32>() < 0.7 {
                        d.extend(noisy(l, 0.15, &mut rng));
                    }
                }
                for _ in 0..60 {
                    d.extend(unit(&mut rng));
                }
                for c in &common {
                    d.extend(noisy(c, 0.15, &mut rng));
                }
                images.push(d);
            }
        }
        let opts = PlaceOptions {
            words: 16,
            ..PlaceOptions::default()
        };
        let refs: Vec<&[f32]> = images.iter().map(|d| d.as_slice()).collect();
        let voc = Vocabulary::train(&refs, &opts).unwrap();
        assert_eq!(voc.len(), 16);
        let vlads: Vec<Vec<f32>> = images.iter().map(|d| voc.vlad(d)).collect();
        for v in &vlads {
            assert!((similarity(v, v) - 1.0).abs() < 1e-4);
        }
        let pairs = retrieve(&vlads, &|_, _| true, 1);
        for i in 0..images.len() {
            let best = pairs
                .iter()
                .filter(|p| p.0 == i || p.1 == i)
                .max_by(|a, b| a.2.total_cmp(&b.2))
                .unwrap();
            let other = if best.0 == i { best.1 } else { best.0 };
            assert_eq!(other / 2, i / 2, "image {i} retrieved {other}: {pairs:?}");
        }
        // Eligibility is honoured: with same-place pairs forbidden, none is returned.
        let pairs = retrieve(&vlads, &|i, j| i / 2 != j / 2, 3);
        assert!(!pairs.is_empty() && pairs.iter().all(|p| p.0 / 2 != p.1 / 2));
        // Too few descriptors for the vocabulary: none, not a panic.
        assert!(Vocabulary::train(&[&images[0][..D * 3]], &opts).is_none());
    }
}
