//! Which images of a split to score when not all of them: an even spread over timesteps
//! *and* cameras.
//!
//! A split's frames are listed timestep by timestep, each with all its cameras, so taking
//! every k-th frame of the list scores the same few cameras at every timestep (with 16
//! cameras and k = 4: cameras 0, 4, 8 and 12 only). [`spread`] instead gives every
//! timestep its share of the images (`count / timesteps`, ±1) and cycles through the
//! cameras in a scrambled order that moves on from one timestep to the next, so that every
//! camera is scored about equally often (`count / cameras`, ±1 when every frame exists),
//! at timesteps all over the split.

use std::collections::BTreeMap;

/// A step through `n` cameras that is coprime with `n` and near `0.618 n`, so consecutive
/// picks land far apart on the rig.
fn scramble_step(n: usize) -> usize {
    fn gcd(a: usize, b: usize) -> usize {
        if b == 0 { a } else { gcd(b, a % b) }
    }
    if n <= 2 {
        return 1;
    }
    let start = ((n as f64) * 0.618).round() as usize;
    (start..start + n)
        .map(|s| s % n)
        .find(|&s| s > 0 && gcd(s, n) == 1)
        .unwrap_or(1)
}

/// `count` of the `frames` (`(timestep, camera)` each; any order, no duplicates) spread
/// evenly over their timesteps and cameras (see the module docs), as indices into
/// `frames` in increasing order. All of them when `count >= frames.len()`.
pub fn spread(frames: &[(usize, usize)], count: usize) -> Vec<usize> {
    let n = frames.len();
    if count >= n {
        return (0..n).collect();
    }
    if count == 0 {
        return Vec::new();
    }
    // Timesteps and cameras in order; the frame of each (timestep, camera).
    let mut at: BTreeMap<usize, BTreeMap<usize, usize>> = BTreeMap::new();
    let mut cams: Vec<usize> = Vec::new();
    for (i, &(t, c)) in frames.iter().enumerate() {
        at.entry(t).or_default().insert(c, i);
        cams.push(c);
    }
    cams.sort_unstable();
    cams.dedup();
    let steps: Vec<&BTreeMap<usize, usize>> = at.values().collect();
    let (nt, nc) = (steps.len(), cams.len());
    let step = scramble_step(nc);
    let order = |j: usize| cams[(j * step) % nc];
    let mut used = vec![false; n];
    let mut picked = Vec::with_capacity(count);
    for i in 0..count {
        // The timestep: centred bins of the split's timesteps.
        let ti = (((2 * i + 1) * nt) / (2 * count)).min(nt - 1);
        // The camera: the scrambled cycle, shifted by one per full cycle.
        let base = i % nc + i / nc;
        let choice = (0..nc)
            .map(|k| order(base + k))
            .find_map(|c| steps[ti].get(&c).copied().filter(|&f| !used[f]));
        if let Some(f) = choice {
            used[f] = true;
            picked.push(f);
        }
    }
    // Where frames were missing, fill up from the unused ones, spread over the list.
    if picked.len() < count {
        let rest: Vec<usize> = (0..n).filter(|&f| !used[f]).collect();
        let need = count - picked.len();
        picked.extend((0..need).map(|k| rest[(2 * k + 1) * rest.len() / (2 * need)]));
    }
    picked.sort_unstable();
    picked
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(timesteps: usize, cameras: &[usize]) -> Vec<(usize, usize)> {
        (0..timesteps)
            .flat_map(|t| cameras.iter().map(move |&c| (t, c)))
            .collect()
    }

    fn counts(frames: &[(usize, usize)], picked: &[usize]) -> (Vec<usize>, Vec<usize>) {
        let nt = frames.iter().map(|f| f.0).max().unwrap_or(0) + 1;
        let nc = frames.iter().map(|f| f.1).max().unwrap_or(0) + 1;
        let (mut t, mut c) = (vec![0; nt], vec![0; nc]);
        for &i in picked {
            t[frames[i].0] += 1;
            c[frames[i].1] += 1;
        }
        (t, c)
    }

    fn distinct(picked: &[usize]) -> bool {
        picked.windows(2).all(|w| w[0] < w[1])
    }

    #[test]
    fn spreads_over_timesteps_and_cameras() {
        let all: Vec<usize> = (0..16).collect();
        // The held-out sequence of the demo: 12 timesteps x 16 cameras, a quarter of it.
        let f = grid(12, &all);
        let p = spread(&f, 48);
        assert_eq!(p.len(), 48);
        assert!(distinct(&p));
        let (t, c) = counts(&f, &p);
        assert!(t.iter().all(|&k| k == 4), "{t:?}");
        assert!(c.iter().all(|&k| k == 3), "{c:?}");
        // Two timesteps, 8 of 32 images: 4 each, 8 different cameras (every 4th frame of
        // the list would score cameras 0, 4, 8 and 12 only).
        let f = grid(2, &all);
        let p = spread(&f, 8);
        let (t, c) = counts(&f, &p);
        assert_eq!(t, vec![4, 4]);
        assert_eq!(c.iter().filter(|&&k| k > 0).count(), 8, "{c:?}");
        // FREE: 24 x 16, 96 images.
        let f = grid(24, &all);
        let p = spread(&f, 96);
        let (t, c) = counts(&f, &p);
        assert!(t.iter().all(|&k| k == 4), "{t:?}");
        assert!(c.iter().all(|&k| k == 6), "{c:?}");
        // A camera is not tied to a phase of the sequence: camera 8 is scored at
        // timesteps of different residues modulo 4.
        let mut res: Vec<usize> = p
            .iter()
            .filter(|&&i| f[i].1 == 8)
            .map(|&i| f[i].0 % 4)
            .collect();
        res.sort_unstable();
        res.dedup();
        assert!(res.len() >= 2, "{res:?}");
    }

    #[test]
    fn one_camera_spreads_over_time_and_gaps_are_filled() {
        // Novel view: camera 8 only, 120 timesteps, 30 images: every 4th timestep.
        let f = grid(120, &[8]);
        let p = spread(&f, 30);
        let ts: Vec<usize> = p.iter().map(|&i| f[i].0).collect();
        assert_eq!(ts.len(), 30);
        assert!(ts.windows(2).all(|w| w[1] - w[0] == 4), "{ts:?}");
        // Missing frames: the count is kept, every index valid and distinct.
        let f: Vec<(usize, usize)> = grid(6, &[0, 1, 2, 3])
            .into_iter()
            .filter(|&(t, c)| t % 2 == 0 || c == 0)
            .collect();
        for count in 0..=f.len() + 2 {
            let p = spread(&f, count);
            assert_eq!(p.len(), count.min(f.len()));
            assert!(distinct(&p));
            assert!(p.iter().all(|&i| i < f.len()));
        }
        assert_eq!(spread(&f, 100), (0..f.len()).collect::<Vec<_>>());
    }
}
