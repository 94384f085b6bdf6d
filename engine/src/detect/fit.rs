//! A region's particles fitted together as spots ([`spots`](super::spots)) to the blurred image,
//! so a particle's image may run under its neighbour's instead of being cut at the boundary
//! between them.

use super::regions::{nearest_pixel, Context, Pixel};
use super::spots::{fit_spots, Spot, SpotFit};
use super::{Detection, Separation};
use crate::geometry::PixelPoint;

/// Two pixels of background around the region pin down the floor and the spots' tails.
const MARGIN_PX: usize = 2;

/// Refines the parts of a split region (`parts`, measured from `region`, label `label`) by a
/// spot fit seeded at their centroids: where the fit is trustworthy the parts take its centres
/// and count as [`Separation::Fitted`]. An untrusted fit changes nothing: its centres, even
/// where they look better placed than the cut's, move the tracks more than they correct them.
pub(super) fn refine_parts(
    context: &Context<'_>,
    region: &[Pixel],
    label: u32,
    parts: &mut [Detection],
) {
    let seeds: Vec<Spot> = parts
        .iter()
        .map(|d| spot_seed(context, d.centroid, d.diameter_px))
        .collect();
    let Some(fit) = fit_to_region(context, region, label, &seeds).filter(SpotFit::is_trustworthy)
    else {
        return;
    };
    for (d, spot) in parts.iter_mut().zip(&fit.spots) {
        d.centroid = PixelPoint {
            x: spot.x,
            y: spot.y,
        };
        d.brightness = context.brightness_at(d.centroid);
        d.separation = d.separation.min(Separation::Fitted);
    }
}

/// A spot to start a fit from: centred at `at`, as bright as the blurred image there, as wide as
/// a disc of `diameter_px` blurred.
pub(super) fn spot_seed(context: &Context<'_>, at: PixelPoint, diameter_px: f64) -> Spot {
    Spot {
        x: at.x,
        y: at.y,
        amplitude: context.blurred[nearest_pixel(context.image, at)] as f64 / 256.0,
        sigma: (diameter_px / 3.5).max(0.8),
        flatness: 1.2,
    }
}

/// Fits spots from `seeds` to region `label` (its pixels `region`) in the blurred image
/// (background model subtracted) over the region and a margin of background around it; pixels
/// of other regions are left out.
pub(super) fn fit_to_region(
    context: &Context<'_>,
    region: &[Pixel],
    label: u32,
    seeds: &[Spot],
) -> Option<SpotFit> {
    let blurred = |j: usize| Some(f64::from(context.blurred[j]) / 256.0);
    fit_spots(&samples_around(context, region, label, blurred), seeds)
}

/// The pixels within the margin of a region as the camera saw them (x, y, grey level), but
/// those at the sensor's full scale (a clipped pixel says only that the light was at least
/// that much).
pub(super) fn raw_samples_around(
    context: &Context<'_>,
    region: &[Pixel],
    label: u32,
) -> Vec<(f64, f64, f64)> {
    let pixels = context.image.pixels;
    let raw = |j: usize| (pixels[j] < u8::MAX).then(|| f64::from(pixels[j]));
    samples_around(context, region, label, raw)
}

/// The pixels within the margin of a region (x, y, and `value` of each, where it has one): its
/// own and the background's, not other regions'. Only those near the region: an elongated
/// region's bounding box is mostly background far from either particle.
fn samples_around(
    context: &Context<'_>,
    region: &[Pixel],
    label: u32,
    value: impl Fn(usize) -> Option<f64>,
) -> Vec<(f64, f64, f64)> {
    let (w, h) = (context.image.width, context.image.height);
    let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
    for p in region {
        x0 = x0.min(p.x);
        y0 = y0.min(p.y);
        x1 = x1.max(p.x);
        y1 = y1.max(p.y);
    }
    let margin = MARGIN_PX;
    let (x0, y0) = (
        (x0 as usize).saturating_sub(margin),
        (y0 as usize).saturating_sub(margin),
    );
    let (x1, y1) = (
        (x1 as usize + margin).min(w - 1),
        (y1 as usize + margin).min(h - 1),
    );
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    let mut near = vec![false; bw * bh];
    for p in region {
        let (px, py) = (p.x as usize - x0, p.y as usize - y0);
        for ny in py.saturating_sub(margin)..=(py + margin).min(bh - 1) {
            let row = ny * bw;
            near[row + px.saturating_sub(margin)..=row + (px + margin).min(bw - 1)].fill(true);
        }
    }
    let (mask, labels) = (context.mask, context.labels);
    let mut samples = Vec::with_capacity(bw * bh);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let j = y * w + x;
            let own = mask[j] == 0 || (mask[j] == 2 && labels[j] == label);
            if !own || !near[(y - y0) * bw + (x - x0)] {
                continue;
            }
            if let Some(v) = value(j) {
                samples.push((x as f64, y as f64, v));
            }
        }
    }
    samples
}
