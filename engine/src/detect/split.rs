//! Regions that hold several particles ([`DetectConfig::split_touching`]): a round region is one
//! particle; an elongated one is several touching or overlapping particles whose merged centroid
//! lies on none of them. It is split between its separated intensity peaks, or failing that cut
//! by intensity-weighted 2-means along its long axis (again, until each part is round), and the
//! parts refined by fitting them together as spots ([`DetectConfig::fit_overlaps`]).
//!
//! [`DetectConfig::split_touching`]: super::DetectConfig::split_touching
//! [`DetectConfig::fit_overlaps`]: super::DetectConfig::fit_overlaps

use super::fit;
use super::regions::{Context, Moments, Pixel};
use super::{Detection, Separation};

/// The most particles one region is split into: the spot fit takes at most four.
pub(super) const MAX_SPOTS_PER_REGION: usize = 4;

/// Measures region `label` (its pixels `region`) into `out`; see [`Separation`] for what each
/// detection is good for.
pub(super) fn resolve(
    context: &Context<'_>,
    region: &[Pixel],
    label: u32,
    out: &mut Vec<Detection>,
) {
    let config = context.config;
    if !is_elongated(context, region) {
        out.extend(context.measure(region));
        return;
    }
    if !config.split_touching {
        return;
    }
    // Parts separated by a dip are particles that touch; parts cut by 2-means overlap, and
    // their centroids are pulled towards each other.
    let (parts, separation) = match split_at_peaks(context, region, label) {
        Some(parts) => (parts, Separation::Clear),
        None => (two_means(context, region), Separation::Cut),
    };
    let (round, complete) = cut_until_round(context, parts, separation);
    let mut measured: Vec<Detection> = round
        .iter()
        .filter_map(|(part, separation)| {
            let d = context.measure(part)?;
            Some(Detection {
                separation: *separation,
                ..d
            })
        })
        .collect();
    // A fit needs every particle of the region, or the missing one's light pulls the rest.
    // Regions cut into three or four parts are only tracked: fitting that many spots costs far
    // more than the few particles it measures, and the tracks that expect particles there still
    // get them fitted (`Detector::separate_expected`). A region a 3D track expects a particle
    // on is left to the tracks' own fits.
    if config.fit_overlaps
        && complete
        && measured.len() == round.len()
        && round.len() <= 2
        && !context.is_tracked(region)
    {
        fit::refine_parts(context, region, label, &mut measured);
    }
    out.extend(measured);
}

/// Whether a region is too elongated to be one particle's image ([`max_axis_ratio`], judged on
/// regions of 12 pixels or more).
///
/// [`max_axis_ratio`]: super::DetectConfig::max_axis_ratio
fn is_elongated(context: &Context<'_>, pixels: &[Pixel]) -> bool {
    let max = context.config.max_axis_ratio;
    max > 0.0 && pixels.len() >= 12 && Moments::of(pixels).axis_ratio() > max
}

/// Cuts the parts that are still elongated again (a chain of three, or a pair inside a cluster),
/// up to the most spots a fit takes; returns the round parts, in the order they were cut, and
/// whether every pixel ended in one. Only what cannot be made round is dropped, not the whole
/// region: a particle that merely touches a cluster keeps its detection.
fn cut_until_round(
    context: &Context<'_>,
    parts: Vec<Vec<Pixel>>,
    separation: Separation,
) -> (Vec<(Vec<Pixel>, Separation)>, bool) {
    let mut round: Vec<(Vec<Pixel>, Separation)> = Vec::new();
    // A stack, so parts come out in the order they were cut.
    let mut pending: Vec<(Vec<Pixel>, Separation)> =
        parts.into_iter().rev().map(|p| (p, separation)).collect();
    let mut complete = true;
    while let Some((part, separation)) = pending.pop() {
        if part.len() < context.config.min_area_px {
            complete = false;
        } else if !is_elongated(context, &part) {
            round.push((part, separation));
        } else if round.len() + pending.len() + 2 <= MAX_SPOTS_PER_REGION {
            pending.extend(
                two_means(context, &part)
                    .into_iter()
                    .rev()
                    .map(|half| (half, Separation::Cut)),
            );
        } else {
            complete = false;
        }
    }
    (round, complete)
}

/// Splits a region in two along its long axis.
fn two_means(context: &Context<'_>, pixels: &[Pixel]) -> Vec<Vec<Pixel>> {
    // Seed the two centres on the long axis, one standard deviation out.
    let m = Moments::of(pixels);
    let (mx, my) = (m.mean_x, m.mean_y);
    let angle = 0.5 * (2.0 * m.xy).atan2(m.xx - m.yy);
    let spread = ((m.xx + m.yy) / pixels.len() as f64).sqrt();
    let (ux, uy) = (angle.cos() * spread, angle.sin() * spread);
    k_means(
        context,
        pixels,
        vec![(mx - ux, my - uy), (mx + ux, my + uy)],
    )
}

/// Intensity-weighted k-means of a region's pixels from the given seeds (a few rounds suffice for
/// the handful of pixels in a particle image).
fn k_means(
    context: &Context<'_>,
    pixels: &[Pixel],
    mut centres: Vec<(f64, f64)>,
) -> Vec<Vec<Pixel>> {
    let points: Vec<(f64, f64, f64)> = pixels
        .iter()
        .map(|p| {
            let weight = context.weight(p.index as usize).max(1e-9);
            (p.x as f64, p.y as f64, weight)
        })
        .collect();
    let mut nearest = vec![0usize; points.len()];
    let mut sums = vec![(0.0, 0.0, 0.0); centres.len()];
    for _ in 0..10 {
        sums.iter_mut().for_each(|s| *s = (0.0, 0.0, 0.0));
        for (&(x, y, v), n) in points.iter().zip(nearest.iter_mut()) {
            let mut best = f64::MAX;
            for (c, &(cx, cy)) in centres.iter().enumerate() {
                let d = (x - cx) * (x - cx) + (y - cy) * (y - cy);
                if d < best {
                    best = d;
                    *n = c;
                }
            }
            let s = &mut sums[*n];
            *s = (s.0 + v, s.1 + v * x, s.2 + v * y);
        }
        let mut moved: f64 = 0.0;
        for (c, &(sw, sx, sy)) in centres.iter_mut().zip(&sums) {
            if sw > 0.0 {
                let next = (sx / sw, sy / sw);
                moved = moved.max((next.0 - c.0).abs() + (next.1 - c.1).abs());
                *c = next;
            }
        }
        if moved < 1e-6 {
            break;
        }
    }
    let mut parts: Vec<Vec<Pixel>> = vec![Vec::new(); centres.len()];
    for (&p, &n) in pixels.iter().zip(&nearest) {
        parts[n].push(p);
    }
    parts
}

/// Splits region `label` between its separated peaks of the blurred image; `None` when it has
/// one peak, or peaks joined without a real dip (a flat-topped disc with noise).
fn split_at_peaks(context: &Context<'_>, region: &[Pixel], label: u32) -> Option<Vec<Vec<Pixel>>> {
    let b = context.blurred;
    let (peaks, floor) = peaks_of(context, region, label);
    // Keep the highest peak of every group whose members are joined without a real dip.
    let at = |p: &Pixel| b[p.index as usize];
    let mut kept: Vec<Pixel> = Vec::new();
    for &p in &peaks {
        let separate = kept.iter().all(|k| {
            let lower = (at(&p).min(at(k)) - floor) as f64;
            let dip = lowest_on_segment(b, context.image.width, &p, k) - floor as f64;
            dip < (1.0 - context.config.split_dip_fraction) * lower
        });
        if separate {
            kept.push(p);
        }
    }
    if kept.len() < 2 {
        return None;
    }
    let seeds = kept.iter().map(|k| (k.x as f64, k.y as f64)).collect();
    Some(k_means(context, region, seeds))
}

/// A region's peak pixels (not lower than any 8-neighbour inside the region), highest first,
/// and its lowest blurred value.
fn peaks_of(context: &Context<'_>, region: &[Pixel], label: u32) -> (Vec<Pixel>, u16) {
    let (w, h) = (context.image.width, context.image.height);
    let b = context.blurred;
    let in_region = |j: usize| context.labels[j] == label;
    let mut peaks: Vec<Pixel> = Vec::new();
    let mut floor = u16::MAX;
    for &p in region {
        let i = p.index as usize;
        floor = floor.min(b[i]);
        let (x, y) = (p.x as usize, p.y as usize);
        let mut is_peak = true;
        'n: for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
            for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                let j = ny * w + nx;
                if j != i && b[j] > b[i] && in_region(j) {
                    is_peak = false;
                    break 'n;
                }
            }
        }
        if is_peak {
            peaks.push(p);
        }
    }
    let at = |p: &Pixel| b[p.index as usize];
    peaks.sort_by(|a, c| at(c).cmp(&at(a)).then(a.index.cmp(&c.index)));
    (peaks, floor)
}

/// The lowest blurred value on the straight line between two pixels.
fn lowest_on_segment(b: &[u16], w: usize, from: &Pixel, to: &Pixel) -> f64 {
    let (x0, y0) = (from.x as f64, from.y as f64);
    let (x1, y1) = (to.x as f64, to.y as f64);
    let steps = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
    (0..=steps)
        .map(|s| {
            let t = s as f64 / steps as f64;
            let (x, y) = ((x0 + t * (x1 - x0)).round(), (y0 + t * (y1 - y0)).round());
            b[y as usize * w + x as usize] as f64
        })
        .fold(f64::MAX, f64::min)
}
