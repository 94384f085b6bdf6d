//! Particles looked for again where the tracks expect them ([`DetectConfig::separate_expected`]):
//! a region holding more expected particles than it gave detections is particles overlapping
//! too closely to part by shape (a merged round blob, a cluster of three), fitted again with
//! one spot seeded at each expected position.
//!
//! [`DetectConfig::separate_expected`]: super::DetectConfig::separate_expected

use super::fit::{fit_to_region, raw_samples_around, spot_seed};
use super::regions::{nearest_pixel, pixel_on, Context, ResolvedRegion};
use super::split::MAX_SPOTS_PER_REGION;
use super::spots::{Spot, SpotFit};
use super::{DetectConfig, Detection, Detector, Separation};
use crate::geometry::PixelPoint;
use crate::ImageView;

/// Tracks expecting particles closer than this are taken to follow the same one.
const MIN_EXPECTED_APART_PX: f64 = 1.0;

/// A region only cut by shape and fitted again from its tracks' expectations: a spot counts as
/// measured only this far from the others (in sums of half widths; trustworthy fits need 1).
/// Closer ones come out pinned by the fit's covariance but biased by the spot model's mismatch.
const CUT_REFIT_MIN_SEPARATION_IN_HALF_WIDTHS: f64 = 0.85;

/// A way to part a region from what its tracks know: given the indices (into the expected
/// positions) of the particles expected on it, its pixels as the camera saw them (x, y, grey
/// level; a margin of background around it, other regions left out) and the diameter of each
/// particle's share of its area, the particles' centres, or `None` where it cannot tell them.
pub type Parting<'p> = &'p dyn Fn(&[usize], &[(f64, f64, f64)], f64) -> Option<Vec<PixelPoint>>;

impl Detector {
    /// Looks again where tracks expect particles (`expected`, raw pixels, e.g. from each track's
    /// motion). Where the fit explains a region's pixels, its spots replace the region's
    /// detections: [`Separation::Fitted`] where the fit is trustworthy, else
    /// [`Separation::Cut`] (good for keeping the tracks, not for measuring). Regions of more than
    /// four expected particles are left as they are. Where `parting` is given, a region is
    /// parted by it instead ([`Separation::Fitted`] detections at its centres), and left as
    /// detected where it cannot tell the particles. Called after [`Self::detect`] on the same
    /// image, with the same `config`, where [`DetectConfig::separate_expected`] asks for it.
    pub fn separate_expected(
        &mut self,
        image: ImageView<'_>,
        config: &DetectConfig,
        expected: &[PixelPoint],
        parting: Option<Parting<'_>>,
        out: &mut Vec<Detection>,
    ) {
        if expected.len() < 2 || self.regions.resolved.is_empty() {
            return;
        }
        let claims = self.claims(image, expected);
        let mut replaced: Vec<(usize, Vec<Detection>)> = Vec::new();
        for group in claims.chunk_by(|a, b| a.0 == b.0) {
            let region = self.regions.resolved[group[0].0];
            let only_cut = is_only_cut(&region, group.len(), out);
            if !worth_refitting(&region, group, expected, only_cut) {
                continue;
            }
            let from = nearest_pixel(image, expected[group[0].1]);
            self.regions.gather_region(image, region.label, from);
            let indices: Vec<usize> = group.iter().map(|&(_, i)| i).collect();
            // A region the tracks' shapes cannot part stays as detected: the tracks measure
            // their particles in it among their neighbours.
            let parts = match parting {
                Some(part) => self.part(image, config, &region, &indices, part),
                None => {
                    let points: Vec<PixelPoint> = indices.iter().map(|&i| expected[i]).collect();
                    self.refit(image, config, &region, &points, only_cut)
                }
            };
            if let Some(parts) = parts {
                replaced.push((group[0].0, parts));
            }
        }
        if !replaced.is_empty() {
            self.replace(replaced, out);
        }
    }

    /// The expected positions (by index) that fall on a measured region of the current
    /// image, with that region's index in `resolved`, sorted by region.
    fn claims(&self, image: ImageView<'_>, expected: &[PixelPoint]) -> Vec<(usize, usize)> {
        let (mask, labels) = (&self.regions.mask, &self.regions.labels);
        let mut claims: Vec<(usize, usize)> = expected
            .iter()
            .enumerate()
            .filter_map(|(i, &p)| {
                let j = pixel_on(image, p)?;
                if mask.get(j) != Some(&2) {
                    return None;
                }
                // Only the current image's measured regions are in `resolved`.
                let r = self
                    .regions
                    .resolved
                    .binary_search_by_key(&labels[j], |r| r.label)
                    .ok()?;
                Some((r, i))
            })
            .collect();
        claims.sort_by_key(|&(r, _)| r);
        claims
    }

    /// The region (whose pixels were just gathered) parted by `part` from the particles
    /// expected on it (`indices`); its new detections, or `None` where `part` cannot tell them.
    fn part(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        region: &ResolvedRegion,
        indices: &[usize],
        part: Parting<'_>,
    ) -> Option<Vec<Detection>> {
        let context = self.context(image, config);
        let pixels = raw_samples_around(&context, &self.regions.region, region.label);
        let share = region.area_px as f64 / indices.len() as f64;
        let diameter_px = (4.0 * share / std::f64::consts::PI).sqrt();
        let centres = part(indices, &pixels, diameter_px)?;
        let parts = centres.into_iter().map(|centroid| Detection {
            centroid,
            diameter_px,
            brightness: context.brightness_at(centroid),
            area_px: share.round() as u32,
            separation: Separation::Fitted,
        });
        Some(parts.collect())
    }

    /// What measuring the current image's regions reads.
    fn context<'c>(&'c self, image: ImageView<'c>, config: &'c DetectConfig) -> Context<'c> {
        Context {
            image,
            config,
            blurred: &self.blur.blurred,
            background: &self.background,
            mask: &self.regions.mask,
            labels: &self.regions.labels,
            tracked: &[],
        }
    }

    /// The region (whose pixels were just gathered) fitted with one spot at each expected
    /// position; its new detections, or `None` where the fit does not explain its pixels.
    fn refit(
        &self,
        image: ImageView<'_>,
        config: &DetectConfig,
        region: &ResolvedRegion,
        expected: &[PixelPoint],
        only_cut: bool,
    ) -> Option<Vec<Detection>> {
        let context = self.context(image, config);
        let share = region.area_px as f64 / expected.len() as f64;
        let diameter_px = (4.0 * share / std::f64::consts::PI).sqrt();
        let seeds: Vec<Spot> = expected
            .iter()
            .map(|&p| spot_seed(&context, p, diameter_px))
            .collect();
        let fit = fit_to_region(&context, &self.regions.region, region.label, &seeds)
            .filter(SpotFit::explains_the_pixels)?;
        let trusted = fit.is_trustworthy();
        let parts = fit.spots.iter().enumerate().map(|(k, spot)| {
            let apart = !only_cut || fit.is_apart(k, CUT_REFIT_MIN_SEPARATION_IN_HALF_WIDTHS);
            let separation = if trusted || (fit.is_measured(k) && apart) {
                Separation::Fitted
            } else {
                Separation::Cut
            };
            let centroid = PixelPoint {
                x: spot.x,
                y: spot.y,
            };
            Detection {
                centroid,
                diameter_px,
                brightness: context.brightness_at(centroid),
                area_px: share.round() as u32,
                separation,
            }
        });
        Some(parts.collect())
    }

    /// Puts each refitted region's new detections (`replaced`, by region index, in order) in
    /// place of its old ones in `out`, keeping the regions' runs of `out` up to date.
    fn replace(&mut self, replaced: Vec<(usize, Vec<Detection>)>, out: &mut Vec<Detection>) {
        let before = std::mem::take(out);
        let mut replaced = replaced.into_iter().peekable();
        for (r, region) in self.regions.resolved.iter_mut().enumerate() {
            let first = out.len();
            match replaced.next_if(|(at, _)| *at == r) {
                Some((_, parts)) => out.extend(parts),
                None => out.extend_from_slice(&before[region.first..region.first + region.count]),
            }
            region.first = first;
            region.count = out.len() - first;
        }
    }
}

/// A region only cut by shape, whose every part a track expects (`expected` of them): it is
/// fitted again from the expectations, as the cut's parts are biased towards each other and the
/// expectations are not.
fn is_only_cut(region: &ResolvedRegion, expected: usize, out: &[Detection]) -> bool {
    expected >= 2
        && expected == region.count
        && out[region.first..region.first + region.count]
            .iter()
            .all(|d| d.separation == Separation::Cut)
}

/// Whether a region with these expectations (`group`) is fitted again: more expected than found,
/// or only cut; at most as many as a fit takes; and distinct (two tracks expecting one spot are
/// one particle followed twice, not two).
fn worth_refitting(
    region: &ResolvedRegion,
    group: &[(usize, usize)],
    expected: &[PixelPoint],
    only_cut: bool,
) -> bool {
    let k = group.len();
    let more_expected_than_found = k > region.count.max(1);
    if !(more_expected_than_found || only_cut) || k > MAX_SPOTS_PER_REGION {
        return false;
    }
    group.iter().enumerate().all(|(i, a)| {
        let a = expected[a.1];
        group[i + 1..].iter().all(|b| {
            let b = expected[b.1];
            (a.x - b.x).hypot(a.y - b.y) >= MIN_EXPECTED_APART_PX
        })
    })
}
