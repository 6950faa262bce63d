//! Tracks: pairwise matches chained into one 3-D point's observations across many images (union-find
//! over every image's features).
//!
//! A wrong match joins two tracks, and on a facade of repeated windows a few of them chain most of the
//! image's features into one component that holds several features of one image: dropping such
//! components (the naive rule) loses most of the data. So the union is built greedily from the most
//! distinctive match to the least (descriptor distance), and a match that would put two features of
//! one image into one track is refused: the wrong link is the one left out, and both tracks live.

/// One feature of one image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct FeatureRef {
    pub image: u32,
    pub feature: u32,
}

/// Disjoint sets with path halving and union by size.
struct UnionFind {
    parent: Vec<u32>,
    size: Vec<u32>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        UnionFind {
            parent: (0..n as u32).collect(),
            size: vec![1; n],
        }
    }

    fn find(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = p;
        }
        x
    }

    fn union(&mut self, a: u32, b: u32) {
        let (mut a, mut b) = (self.find(a), self.find(b));
        if a == b {
            return;
        }
        if self.size[a as usize] < self.size[b as usize] {
            std::mem::swap(&mut a, &mut b);
        }
        self.parent[b as usize] = a;
        self.size[a as usize] += self.size[b as usize];
    }
}

/// Feature matches of one image pair `(i, j)`: (feature in i, feature in j, descriptor distance).
pub type PairMatches = ((usize, usize), Vec<(u32, u32, f32)>);

/// What [`build_tracks`] kept and dropped.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct TrackStats {
    pub tracks: usize,
    pub observations: usize,
    /// Matches refused for joining two features of one image into a track.
    pub refused_matches: usize,
    pub mean_length: f64,
}

/// Tracks of at least two images from `matches` (image pairs and their feature matches with descriptor
/// distances); `features_per_image[i]` is image i's feature count. Each track is sorted by image.
pub fn build_tracks(
    features_per_image: &[usize],
    matches: &[PairMatches],
) -> (Vec<Vec<FeatureRef>>, TrackStats) {
    let mut offset = Vec::with_capacity(features_per_image.len() + 1);
    let mut total = 0usize;
    for &n in features_per_image {
        offset.push(total);
        total += n;
    }
    offset.push(total);
    let mut uf = UnionFind::new(total);
    let mut touched = vec![false; total];
    // The images each root's track holds (sorted, small).
    let mut images: Vec<Vec<u32>> = (0..total).map(|_| Vec::new()).collect();
    let mut all: Vec<(f32, u32, u32, u32, u32)> = Vec::new();
    for ((i, j), m) in matches {
        for &(a, b, d) in m {
            if (a as usize) >= features_per_image[*i] || (b as usize) >= features_per_image[*j] {
                continue;
            }
            let ga = (offset[*i] + a as usize) as u32;
            let gb = (offset[*j] + b as usize) as u32;
            all.push((d, ga, gb, *i as u32, *j as u32));
        }
    }
    all.sort_by(|x, y| x.0.total_cmp(&y.0).then((x.1, x.2).cmp(&(y.1, y.2))));
    let mut stats = TrackStats::default();
    for &(_, ga, gb, i, j) in &all {
        for (g, im) in [(ga, i), (gb, j)] {
            if !touched[g as usize] {
                touched[g as usize] = true;
                images[g as usize] = vec![im];
            }
        }
        let (ra, rb) = (uf.find(ga), uf.find(gb));
        if ra == rb {
            continue;
        }
        let (sa, sb) = (&images[ra as usize], &images[rb as usize]);
        if sa.iter().any(|x| sb.binary_search(x).is_ok()) {
            stats.refused_matches += 1;
            continue;
        }
        let mut merged: Vec<u32> = sa.iter().chain(sb).copied().collect();
        merged.sort_unstable();
        uf.union(ga, gb);
        let root = uf.find(ga);
        images[ra as usize].clear();
        images[rb as usize].clear();
        images[root as usize] = merged;
    }
    let image_of = |g: usize| offset.partition_point(|&o| o <= g) - 1;
    let mut groups: std::collections::HashMap<u32, Vec<FeatureRef>> =
        std::collections::HashMap::new();
    for (g, _) in touched.iter().enumerate().filter(|(_, &t)| t) {
        let root = uf.find(g as u32);
        let image = image_of(g);
        groups.entry(root).or_default().push(FeatureRef {
            image: image as u32,
            feature: (g - offset[image]) as u32,
        });
    }
    let mut roots: Vec<u32> = groups.keys().copied().collect();
    roots.sort_unstable();
    let mut tracks = Vec::new();
    for r in roots {
        let mut t = groups.remove(&r).unwrap_or_default();
        t.sort_unstable();
        debug_assert!(t.windows(2).all(|w| w[0].image != w[1].image));
        if t.len() >= 2 {
            stats.observations += t.len();
            tracks.push(t);
        }
    }
    stats.tracks = tracks.len();
    stats.mean_length = if tracks.is_empty() {
        0.0
    } else {
        stats.observations as f64 / tracks.len() as f64
    };
    (tracks, stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f(image: u32, feature: u32) -> FeatureRef {
        FeatureRef { image, feature }
    }

    /// 0-1 and 1-2 matches chain into one three-image track; the weakest match that would bring a
    /// second feature of image 0 into a track is the one refused, and the rest survive.
    #[test]
    fn chains_matches_and_refuses_the_link_that_makes_a_track_inconsistent() {
        let n = [5, 5, 5];
        let matches = vec![
            ((0, 1), vec![(0, 1, 0.1), (2, 2, 0.2), (3, 4, 0.1)]),
            ((1, 2), vec![(1, 3, 0.1), (2, 0, 0.2)]),
            // 0:4 – 2:0 would join 0:4 to the track of 0:2 (through 1:2 and 2:0): refused, as the least
            // distinctive of the three links.
            ((0, 2), vec![(4, 0, 0.5)]),
        ];
        let (tracks, stats) = build_tracks(&n, &matches);
        assert_eq!(
            tracks,
            vec![
                vec![f(0, 0), f(1, 1), f(2, 3)],
                vec![f(0, 2), f(1, 2), f(2, 0)],
                vec![f(0, 3), f(1, 4)]
            ],
            "{stats:?}"
        );
        assert_eq!(stats.refused_matches, 1);
        assert_eq!(stats.observations, 8);
        // The same wrong link, now the most distinctive: it is kept, the later link 1:2 – 2:0 is the one
        // refused, and still no track holds two features of one image.
        let mut m2 = matches.clone();
        m2[2].1[0].2 = 0.01;
        let (tracks, stats) = build_tracks(&n, &m2);
        assert_eq!(stats.refused_matches, 1);
        for t in &tracks {
            assert!(t.windows(2).all(|w| w[0].image != w[1].image), "{t:?}");
        }
        // Out-of-range indices are ignored, not a panic.
        let (t, _) = build_tracks(&n, &[((0, 1), vec![(9, 0, 0.1)])]);
        assert!(t.is_empty());
    }
}
