//! The `sparse` image encoding of frame messages (`protocol/README.md`): every pixel that can
//! belong to a particle, exactly, and the background only as one level per block. A headset's
//! Wi-Fi cannot carry raw or PNG pairs at 30 Hz (sensor noise does not compress), but particles
//! cover a few percent of an image: sent this way, what the detector measures (each particle's
//! pixels, and the local mean it is thresholded against) arrives unchanged, at a tenth of PNG's
//! size or less. Pure, no I/O.
//!
//! Layout of one image (little-endian):
//! - `u8 block_px` (>= 1), three bytes 0, `u32 run_count`;
//! - `ceil(width / block_px) * ceil(height / block_px)` background levels, `u8`, row-major;
//! - `run_count` runs of kept pixels, each `u32 start` (`y * width + x`) and `u16 length` (>= 1),
//!   in raster order, not overlapping, each within one row;
//! - the runs' pixels, in run order: as many bytes as the runs' lengths add up to.
//!
//! The receiver paints the background by bilinear interpolation between block centres
//! ([`paint_background`]), then the runs over it.

/// Encoder settings; the receiver needs none of them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SparseParams {
    /// Side of the square blocks the background is sent by, pixels.
    pub(crate) block_px: u8,
    /// A pixel is kept (with its surroundings) where the mean of its 3x3 neighbourhood stands
    /// this many grey levels above the background. The detector's own threshold is 6 above the
    /// local mean of the blurred image (`detect.contrast_c`); the 3x3 mean cuts sensor noise by
    /// three, so 4 keeps every pixel the detector can find without keeping noise.
    pub(crate) threshold: u8,
    /// Kept pixels are grown by this many pixels each way, so a particle's rim, the detector's
    /// 5x5 blur around it and the pixels the fits read around it (its edge plus three edge
    /// widths and a 2-pixel margin) arrive exact: a fit reading the painted background, where
    /// a block half covered by a particle paints a halo, is pulled off the particle.
    pub(crate) margin_px: u8,
}

impl Default for SparseParams {
    fn default() -> Self {
        Self {
            block_px: 16,
            threshold: 4,
            margin_px: 5,
        }
    }
}

const HEADER_BYTES: usize = 8;
const RUN_BYTES: usize = 6;

fn blocks(width: usize, height: usize, block_px: usize) -> (usize, usize) {
    (width.div_ceil(block_px), height.div_ceil(block_px))
}

/// Fills an image with the background given per block: bilinear between block centres,
/// constant beyond the outer centres. Encoder and decoder share it, so the encoder judges
/// pixels against the background the receiver will see.
pub(crate) fn paint_background(
    levels: &[u8],
    width: usize,
    height: usize,
    block_px: usize,
) -> Vec<u8> {
    let (bw, bh) = blocks(width, height, block_px);
    // Per axis: for each pixel, the two block indices and the weight of the second.
    let axis = |n: usize, blocks: usize| -> Vec<(usize, usize, f32)> {
        (0..n)
            .map(|p| {
                let f = (p as f32 + 0.5) / block_px as f32 - 0.5;
                let f = f.clamp(0.0, (blocks - 1) as f32);
                let i = (f.floor() as usize).min(blocks - 1);
                let j = (i + 1).min(blocks - 1);
                (i, j, f - i as f32)
            })
            .collect()
    };
    let (xs, ys) = (axis(width, bw), axis(height, bh));
    let mut image = vec![0u8; width * height];
    let mut blended = vec![0f32; bw];
    for (y, &(y0, y1, ty)) in ys.iter().enumerate() {
        let (row0, row1) = (
            &levels[y0 * bw..(y0 + 1) * bw],
            &levels[y1 * bw..(y1 + 1) * bw],
        );
        for ((b, &a), &c) in blended.iter_mut().zip(row0).zip(row1) {
            *b = f32::from(a) * (1.0 - ty) + f32::from(c) * ty + 0.5;
        }
        for (out, &(x0, x1, tx)) in image[y * width..(y + 1) * width].iter_mut().zip(&xs) {
            // Truncating v + 0.5 rounds: levels are never negative.
            *out = (blended[x0] + (blended[x1] - blended[x0]) * tx) as u8;
        }
    }
    image
}

/// The median of each block: the background under a few particles.
fn block_medians(pixels: &[u8], width: usize, height: usize, block_px: usize) -> Vec<u8> {
    let (bw, bh) = blocks(width, height, block_px);
    let mut levels = Vec::with_capacity(bw * bh);
    let mut histogram = [0u32; 256];
    for by in 0..bh {
        for bx in 0..bw {
            histogram.fill(0);
            let (x0, y0) = (bx * block_px, by * block_px);
            let (x1, y1) = ((x0 + block_px).min(width), (y0 + block_px).min(height));
            for y in y0..y1 {
                for &p in &pixels[y * width + x0..y * width + x1] {
                    histogram[usize::from(p)] += 1;
                }
            }
            let half = ((x1 - x0) * (y1 - y0)).div_ceil(2) as u32;
            let mut seen = 0;
            let median = histogram
                .iter()
                .position(|&count| {
                    seen += count;
                    seen >= half
                })
                .unwrap_or(0);
            levels.push(median as u8);
        }
    }
    levels
}

/// Grows a mask by `r` pixels each way (a square): a running count along each row, then one
/// down the columns, a row at a time.
fn dilate(mask: &[bool], width: usize, height: usize, r: usize) -> Vec<bool> {
    let mut rows = vec![false; mask.len()];
    for (line, out) in mask.chunks_exact(width).zip(rows.chunks_exact_mut(width)) {
        let mut count = 0usize;
        for i in 0..width + r {
            if i < width && line[i] {
                count += 1;
            }
            if i > 2 * r && line[i - 2 * r - 1] {
                count -= 1;
            }
            if i >= r {
                out[i - r] = count > 0;
            }
        }
    }
    let mut out = vec![false; mask.len()];
    let mut counts = vec![0u32; width];
    for y in 0..height + r {
        if y < height {
            for (c, &m) in counts.iter_mut().zip(&rows[y * width..(y + 1) * width]) {
                *c += u32::from(m);
            }
        }
        if y > 2 * r {
            let gone = y - 2 * r - 1;
            for (c, &m) in counts
                .iter_mut()
                .zip(&rows[gone * width..(gone + 1) * width])
            {
                *c -= u32::from(m);
            }
        }
        if y >= r {
            let at = y - r;
            for (o, &c) in out[at * width..(at + 1) * width].iter_mut().zip(&counts) {
                *o = c > 0;
            }
        }
    }
    out
}

/// Sums over each pixel's 3x3 neighbourhood, edges repeated.
fn sums_3x3(pixels: &[u8], width: usize, height: usize) -> Vec<u16> {
    let mut across = vec![0u16; pixels.len()];
    for (row, out) in pixels
        .chunks_exact(width)
        .zip(across.chunks_exact_mut(width))
    {
        for x in 0..width {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(width - 1));
            out[x] = u16::from(row[l]) + u16::from(row[x]) + u16::from(row[r]);
        }
    }
    let mut sums = vec![0u16; pixels.len()];
    for y in 0..height {
        let (up, down) = (y.saturating_sub(1), (y + 1).min(height - 1));
        let (a, b, c) = (
            &across[up * width..(up + 1) * width],
            &across[y * width..(y + 1) * width],
            &across[down * width..(down + 1) * width],
        );
        for (x, out) in sums[y * width..(y + 1) * width].iter_mut().enumerate() {
            *out = a[x] + b[x] + c[x];
        }
    }
    sums
}

/// Encodes one 8-bit grayscale image (`width * height` bytes, row-major).
pub(crate) fn encode(pixels: &[u8], width: u32, height: u32, params: &SparseParams) -> Vec<u8> {
    let (w, h) = (width as usize, height as usize);
    debug_assert_eq!(pixels.len(), w * h);
    let block = usize::from(params.block_px.max(1));
    let levels = block_medians(pixels, w, h, block);
    let background = paint_background(&levels, w, h, block);
    let threshold = 9 * u16::from(params.threshold);
    let keep: Vec<bool> = sums_3x3(pixels, w, h)
        .iter()
        .zip(&background)
        .map(|(&sum, &level)| sum > 9 * u16::from(level) + threshold)
        .collect();
    let keep = dilate(&keep, w, h, usize::from(params.margin_px));
    let mut runs: Vec<(u32, u16)> = Vec::new();
    for y in 0..h {
        let mut x = 0;
        while x < w {
            if !keep[y * w + x] {
                x += 1;
                continue;
            }
            let start = x;
            while x < w && keep[y * w + x] && x - start < usize::from(u16::MAX) {
                x += 1;
            }
            runs.push(((y * w + start) as u32, (x - start) as u16));
        }
    }
    let kept: usize = runs.iter().map(|r| usize::from(r.1)).sum();
    let mut out = Vec::with_capacity(HEADER_BYTES + levels.len() + runs.len() * RUN_BYTES + kept);
    out.extend_from_slice(&[params.block_px.max(1), 0, 0, 0]);
    out.extend_from_slice(&(runs.len() as u32).to_le_bytes());
    out.extend_from_slice(&levels);
    for (start, length) in &runs {
        out.extend_from_slice(&start.to_le_bytes());
        out.extend_from_slice(&length.to_le_bytes());
    }
    for (start, length) in &runs {
        let start = *start as usize;
        out.extend_from_slice(&pixels[start..start + usize::from(*length)]);
    }
    out
}

/// Decodes one image of a known size; the error says what is wrong.
pub(crate) fn decode(bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>, String> {
    let (w, h) = (width as usize, height as usize);
    if bytes.len() < HEADER_BYTES {
        return Err(format!(
            "{} bytes, shorter than the {HEADER_BYTES}-byte sparse header",
            bytes.len()
        ));
    }
    let block = usize::from(bytes[0]);
    if block == 0 {
        return Err("block_px is 0".into());
    }
    if bytes[1..4] != [0, 0, 0] {
        return Err("reserved header bytes are not 0".into());
    }
    let run_count = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]) as usize;
    let (bw, bh) = blocks(w, h, block);
    let levels_end = HEADER_BYTES + bw * bh;
    let runs_end = run_count
        .checked_mul(RUN_BYTES)
        .and_then(|n| n.checked_add(levels_end))
        .filter(|&end| end <= bytes.len())
        .ok_or_else(|| {
            format!(
                "{} bytes cannot hold {bw}x{bh} background levels and {run_count} runs",
                bytes.len()
            )
        })?;
    let mut image = paint_background(&bytes[HEADER_BYTES..levels_end], w, h, block);
    let mut pixels = &bytes[runs_end..];
    let mut next_free = 0usize;
    for (k, run) in bytes[levels_end..runs_end]
        .chunks_exact(RUN_BYTES)
        .enumerate()
    {
        let start = u32::from_le_bytes([run[0], run[1], run[2], run[3]]) as usize;
        let length = usize::from(u16::from_le_bytes([run[4], run[5]]));
        let end = start + length;
        if length == 0 || start < next_free || end > w * h || start / w != (end - 1) / w {
            return Err(format!(
                "run {k} (start {start}, length {length}) is empty, out of raster order, overlapping, beyond the image or across rows"
            ));
        }
        if pixels.len() < length {
            return Err(format!("run {k}: its pixels are missing"));
        }
        image[start..end].copy_from_slice(&pixels[..length]);
        pixels = &pixels[length..];
        next_free = end;
    }
    if !pixels.is_empty() {
        return Err(format!(
            "{} bytes after the last run's pixels",
            pixels.len()
        ));
    }
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sloping background with noise and a few bright blobs.
    fn scene(w: usize, h: usize) -> Vec<u8> {
        let mut state = 12345u64;
        let mut noise = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) % 5) as f64 - 2.0
        };
        let blobs = [(20.0, 15.0), (50.5, 30.2), (70.3, 8.7)];
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let mut v = 20.0 + 0.2 * x as f64 + 0.1 * y as f64;
                for (bx, by) in blobs {
                    let d2 = (x as f64 - bx).powi(2) + (y as f64 - by).powi(2);
                    v += 150.0 * (-d2 / 4.0).exp();
                }
                v
            })
            .map(|v| (v + noise()).clamp(0.0, 255.0) as u8)
            .collect()
    }

    #[test]
    fn particles_arrive_exact_and_the_background_close() {
        let (w, h) = (90usize, 40usize);
        let image = scene(w, h);
        let bytes = encode(&image, w as u32, h as u32, &SparseParams::default());
        assert!(bytes.len() < w * h / 2, "{} bytes", bytes.len());
        let back = decode(&bytes, w as u32, h as u32).expect("decodes");
        for (bx, by) in [(20usize, 15usize), (50, 30), (70, 9)] {
            for y in by - 4..=by + 4 {
                for x in bx - 4..=bx + 4 {
                    assert_eq!(back[y * w + x], image[y * w + x], "({x}, {y})");
                }
            }
        }
        let worst = image
            .iter()
            .zip(&back)
            .map(|(a, b)| (i16::from(*a) - i16::from(*b)).abs())
            .max();
        assert!(worst <= Some(6), "background within noise: {worst:?}");
    }

    /// The painted level is the exact bilinear value rounded half up: with `block_px` 16 every
    /// weight is a multiple of 1/32, so the exact value times 1024 is an integer.
    #[test]
    fn the_background_is_the_exact_bilinear_value_rounded_half_up() {
        // 0 and 16 one block apart, a 32nd of the way: 0.5, which rounds up.
        assert_eq!(paint_background(&[0, 16], 32, 1, 16)[8], 1);
        let (w, h, block) = (48usize, 40usize, 16usize);
        let (bw, bh) = blocks(w, h, block);
        let levels: Vec<u8> = (0..bw * bh).map(|k| (k * 37 % 251) as u8).collect();
        // Per pixel, the block pair and the second's weight in 32nds.
        let axis = |p: usize, n: usize| {
            let f = (2 * p as i64 - 15).clamp(0, 32 * (n as i64 - 1));
            let i = (f / 32) as usize;
            (i, (i + 1).min(n - 1), f % 32)
        };
        let painted = paint_background(&levels, w, h, block);
        for y in 0..h {
            let (y0, y1, ty) = axis(y, bh);
            for x in 0..w {
                let (x0, x1, tx) = axis(x, bw);
                let l = |bx: usize, by: usize| i64::from(levels[by * bw + bx]);
                let along_y = |bx| l(bx, y0) * (32 - ty) + l(bx, y1) * ty;
                let v1024 = along_y(x0) * (32 - tx) + along_y(x1) * tx;
                let expected = (v1024 + 512).div_euclid(1024);
                assert_eq!(i64::from(painted[y * w + x]), expected, "({x}, {y})");
            }
        }
    }

    /// A block of an even number of pixels is sent as its lower median.
    #[test]
    fn a_block_level_is_its_lower_median() {
        // One 4x4 block over a 4x2 image: eight pixels, four of 10 and four of 20.
        let pixels = [10, 20, 10, 20, 20, 10, 20, 10];
        assert_eq!(block_medians(&pixels, 4, 2, 4), vec![10]);
        assert_eq!(block_medians(&[10, 20, 20, 30], 2, 2, 2), vec![20]);
    }

    /// The 3x3 mean at the image's border repeats the edge pixels.
    #[test]
    fn the_3x3_mean_repeats_the_border() {
        // The corner pixel counts four times in its own neighbourhood, twice in its neighbour's.
        assert_eq!(sums_3x3(&[9, 0, 0, 0], 2, 2), vec![36, 18, 18, 9]);
    }

    #[test]
    fn a_flat_image_is_its_background_alone() {
        let image = vec![40u8; 64 * 48];
        let bytes = encode(&image, 64, 48, &SparseParams::default());
        assert_eq!(bytes.len(), HEADER_BYTES + 4 * 3);
        assert_eq!(decode(&bytes, 64, 48).expect("decodes"), image);
    }

    #[test]
    fn malformed_images_are_refused_with_a_reason() {
        let (w, h) = (90u32, 40u32);
        let good = encode(&scene(90, 40), w, h, &SparseParams::default());
        assert!(decode(&good[..good.len() - 1], w, h).is_err());
        let mut long = good.clone();
        long.push(0);
        assert!(decode(&long, w, h)
            .unwrap_err()
            .contains("after the last run"));
        let mut zero_block = good.clone();
        zero_block[0] = 0;
        assert!(decode(&zero_block, w, h).is_err());
        let mut reserved = good.clone();
        reserved[2] = 1;
        assert!(decode(&reserved, w, h).is_err());
        let mut many_runs = good.clone();
        many_runs[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode(&many_runs, w, h).is_err());
        // The first run moved across a row's end.
        let levels = HEADER_BYTES + 6 * 3;
        let mut across = good.clone();
        across[levels..levels + 4].copy_from_slice(&(w - 1).to_le_bytes());
        assert!(decode(&across, w, h).unwrap_err().contains("across rows"));
        for n in 0..good.len().min(64) {
            assert!(decode(&good[..n], w, h).is_err(), "{n} bytes");
        }
    }
}
