//! The method's 5x5 Gaussian blur: OpenCV's fixed binomial kernel for `ksize = 5, sigma = 0`,
//! separable, kept unrounded (scaled by 256, the kernel's sum).

use super::background::Background;
use super::threshold::Tiles;
use crate::ImageView;

/// The blurred image and the ring of row passes it is made through.
#[derive(Debug, Default)]
pub(super) struct Blur {
    /// Ring of five horizontally blurred rows.
    row_pass: Vec<u16>,
    /// Blurred image scaled by 256 (the binomial kernel's sum), kept unrounded.
    pub(super) blurred: Vec<u16>,
}

impl Blur {
    /// Blurs `image` through a ring of five row-pass rows, so the intermediate image never
    /// leaves the cache; takes the background model out of each blurred row (updating it with
    /// the row first) when `rise` is not 0, and records each tile's range in `tiles` on the way.
    pub(super) fn run(
        &mut self,
        image: ImageView<'_>,
        background: &mut Background,
        rise: u16,
        tiles: &mut Tiles,
    ) {
        let (w, h) = (image.width, image.height);
        let px = image.pixels;
        self.row_pass.resize(5 * w, 0);
        self.blurred.resize(w * h, 0);
        tiles.reset(w, h);
        let ring_row = |y: usize| (y % 5) * w;
        let mut computed = 0;
        for y in 0..h {
            // Rows y-2..=y+2 (clamped) must be in the ring; they are the last five computed.
            while computed <= (y + 2).min(h - 1) {
                let r = ring_row(computed);
                row_pass(
                    &px[computed * w..(computed + 1) * w],
                    &mut self.row_pass[r..r + w],
                );
                computed += 1;
            }
            let tmp = &self.row_pass;
            let rows = [
                y as isize - 2,
                y as isize - 1,
                y as isize,
                y as isize + 1,
                y as isize + 2,
            ]
            .map(|r| ring_row(r.clamp(0, h as isize - 1) as usize))
            .map(|r| &tmp[r..r + w]);
            let dst = &mut self.blurred[y * w..(y + 1) * w];
            column_pass(rows, dst);
            if rise > 0 {
                background.subtract_row(y * w..(y + 1) * w, dst, rise);
            }
            tiles.record_row(y, dst);
        }
    }
}

/// The horizontal pass of one row, borders replicated.
fn row_pass(src: &[u8], dst: &mut [u16]) {
    let w = src.len();
    let clamp_x = |x: isize| x.clamp(0, w as isize - 1) as usize;
    // Shifted slices instead of indexing, so the compiler drops bounds checks and vectorises.
    if w >= 5 {
        let n = w - 4;
        let taps = [
            &src[0..n],
            &src[1..n + 1],
            &src[2..n + 2],
            &src[3..n + 3],
            &src[4..n + 4],
        ];
        for (((d, (a, b)), (c, e)), f) in dst[2..w - 2]
            .iter_mut()
            .zip(taps[0].iter().zip(taps[1]))
            .zip(taps[2].iter().zip(taps[3]))
            .zip(taps[4])
        {
            *d = *a as u16 + 4 * *b as u16 + 6 * *c as u16 + 4 * *e as u16 + *f as u16;
        }
    }
    for x in (0..w.min(2)).chain(w.saturating_sub(2).max(w.min(2))..w) {
        dst[x] = kernel(|k| src[clamp_x(x as isize + k)] as u16);
    }
}

/// The vertical pass of one row from the row passes of rows y-2..=y+2.
fn column_pass(rows: [&[u16]; 5], dst: &mut [u16]) {
    for ((((d, a), b), c), (e, f)) in dst
        .iter_mut()
        .zip(rows[0])
        .zip(rows[1])
        .zip(rows[2])
        .zip(rows[3].iter().zip(rows[4]))
    {
        *d = a + 4 * b + 6 * c + 4 * e + f;
    }
}

fn kernel(sample: impl Fn(isize) -> u16) -> u16 {
    sample(-2) + 4 * sample(-1) + 6 * sample(0) + 4 * sample(1) + sample(2)
}
