//! Triangles and points into a colour buffer with a depth buffer.

use image::RgbImage;

use super::camera::NEAR_PLANE;

/// A screen-space vertex: pixel x, pixel y (down), inverse depth.
pub(super) type ScreenVertex = [f32; 3];

/// The image being drawn and its depth buffer. Depth is stored as inverse depth (0 = nothing
/// drawn yet): it interpolates linearly in screen space, so triangles need no perspective
/// correction, and larger means nearer.
pub(super) struct Target {
    image: RgbImage,
    inv_depth: Vec<f32>,
}

impl Target {
    /// A target filled with `background`. The caller has checked the size against the limits.
    pub fn new(width: u32, height: u32, background: [u8; 3]) -> Self {
        let image = RgbImage::from_pixel(width, height, image::Rgb(background));
        Self { image, inv_depth: vec![0.0; width as usize * height as usize] }
    }

    pub fn into_image(self) -> RgbImage {
        self.image
    }

    fn width(&self) -> usize {
        self.image.width() as usize
    }

    fn height(&self) -> usize {
        self.image.height() as usize
    }

    /// Writes the pixel at buffer index `i` if `inv_depth` is nearer than what is there.
    fn plot(&mut self, i: usize, inv_depth: f32, color: [u8; 3]) {
        if let Some(z) = self.inv_depth.get_mut(i)
            && inv_depth > *z
        {
            *z = inv_depth;
            if let Some(px) = self.image.get_mut(3 * i..3 * i + 3) {
                px.copy_from_slice(&color);
            }
        }
    }

    /// Fills a screen-space triangle of either winding. A pixel is covered when its centre is
    /// inside or on an edge. Degenerate and non-finite triangles draw nothing.
    pub fn fill_triangle(&mut self, [a, b, c]: [ScreenVertex; 3], color: [u8; 3]) {
        let mut edges = [Edge::new(b, c), Edge::new(c, a), Edge::new(a, b)];
        // Twice the signed area: the third edge's function at the opposite corner.
        let mut area = edges[2].at(f64::from(c[0]), f64::from(c[1]));
        if area < 0.0 {
            // The other winding: flip every edge so that the inside is where all are >= 0.
            area = -area;
            edges = edges.map(Edge::flipped);
        }
        if !(area > 0.0 && area.is_finite()) {
            return;
        }
        let Some((xs, ys)) = self.pixel_range(
            [a[0].min(b[0]).min(c[0]), a[1].min(b[1]).min(c[1])],
            [a[0].max(b[0]).max(c[0]), a[1].max(b[1]).max(c[1])],
        ) else {
            return;
        };
        let width = self.width();
        let depths = [a[2], b[2], c[2]].map(|z| f64::from(z) / area);
        for y in ys {
            let py = y as f64 + 0.5;
            let rows = edges.map(|e| e.b * py + e.c);
            for x in xs.clone() {
                let px = x as f64 + 0.5;
                let e = [0, 1, 2].map(|k| edges[k].a * px + rows[k]);
                if e[0] >= 0.0 && e[1] >= 0.0 && e[2] >= 0.0 {
                    let z = e[0] * depths[0] + e[1] * depths[1] + e[2] * depths[2];
                    self.plot(y * width + x, z as f32, color);
                }
            }
        }
    }

    /// A disc of `radius` pixels at one depth around a screen-space point. It covers at least
    /// the pixel its centre falls in, so that points smaller than a pixel still show.
    pub fn fill_disc(&mut self, p: ScreenVertex, radius: f32, color: [u8; 3]) {
        let width = self.width();
        if p[0] >= 0.0 && p[1] >= 0.0 {
            // Saturating casts: a far-off point gives an index past the image, checked here.
            let (x, y) = (p[0] as usize, p[1] as usize);
            if x < width && y < self.height() {
                self.plot(y * width + x, p[2], color);
            }
        }
        let Some((xs, ys)) =
            self.pixel_range([p[0] - radius, p[1] - radius], [p[0] + radius, p[1] + radius])
        else {
            return;
        };
        let r2 = radius * radius;
        for y in ys {
            let dy = y as f32 + 0.5 - p[1];
            for x in xs.clone() {
                let dx = x as f32 + 0.5 - p[0];
                if dx * dx + dy * dy <= r2 {
                    self.plot(y * width + x, p[2], color);
                }
            }
        }
    }

    /// The pixels whose centres lie in the box `lo..=hi`, clipped to the image; `None` when
    /// that is empty (or the box is not finite).
    fn pixel_range(
        &self,
        lo: [f32; 2],
        hi: [f32; 2],
    ) -> Option<(std::ops::Range<usize>, std::ops::Range<usize>)> {
        let axis = |lo: f32, hi: f32, size: usize| {
            let first = (lo - 0.5).ceil().max(0.0);
            let last = (hi - 0.5).floor().min(size as f32 - 1.0);
            // Also false for NaN. The casts are exact: both ends are in 0..size.
            (first <= last).then(|| first as usize..last as usize + 1)
        };
        Some((axis(lo[0], hi[0], self.width())?, axis(lo[1], hi[1], self.height())?))
    }
}

/// The edge function `a x + b y + c` of a directed edge: twice the signed area of the
/// triangle (p, q, (x, y)), zero on the edge's line.
///
/// Watertightness: two triangles that share an edge traverse it in opposite directions. The
/// coefficients are computed from the endpoints in one canonical order and negated for the
/// other direction, so the two triangles' functions are exact negatives of each other at every
/// pixel (f64 rounding is symmetric) and no pixel along a shared edge is missed by both, even
/// when clipping at the near plane puts corners millions of pixels away. For the same reason
/// each pixel's value is computed, not accumulated in steps.
#[derive(Clone, Copy)]
struct Edge {
    a: f64,
    b: f64,
    c: f64,
}

impl Edge {
    fn new(p: ScreenVertex, q: ScreenVertex) -> Self {
        let key = |v: ScreenVertex| [v[0], v[1]];
        let swapped = key(q) < key(p);
        let (p, q) = if swapped { (q, p) } else { (p, q) };
        let [px, py, qx, qy] = [p[0], p[1], q[0], q[1]].map(f64::from);
        let edge = Self { a: -(qy - py), b: qx - px, c: (qy - py) * px - (qx - px) * py };
        if swapped { edge.flipped() } else { edge }
    }

    fn flipped(self) -> Self {
        Self { a: -self.a, b: -self.b, c: -self.c }
    }

    fn at(&self, x: f64, y: f64) -> f64 {
        self.a * x + self.b * y + self.c
    }
}

/// The part of a camera-space triangle `(x, y, depth)` in front of the near plane, as a convex
/// polygon of 0, 3 or 4 corners (Sutherland-Hodgman against one plane).
pub(super) fn clip_near(tri: [[f32; 3]; 3]) -> ([[f32; 3]; 4], usize) {
    let mut out = [[0.0; 3]; 4];
    let mut n = 0;
    let mut push = |p: [f32; 3]| {
        // A triangle cut by one plane has at most 4 corners, so this never drops one.
        if let Some(slot) = out.get_mut(n) {
            *slot = p;
            n += 1;
        }
    };
    for i in 0..3 {
        let (p, q) = (tri[i], tri[(i + 1) % 3]);
        let (p_in, q_in) = (p[2] >= NEAR_PLANE, q[2] >= NEAR_PLANE);
        if p_in {
            push(p);
        }
        if p_in != q_in {
            // Always from the inside corner, so that the faces sharing this edge compute the
            // very same point (see `Edge` on watertightness).
            let (i, o) = if p_in { (p, q) } else { (q, p) };
            let t = (NEAR_PLANE - i[2]) / (o[2] - i[2]);
            push(std::array::from_fn(|k| i[k] + t * (o[k] - i[k])));
        }
    }
    (out, n)
}

#[cfg(test)]
mod tests {
    use super::*;

    const WHITE: [u8; 3] = [255; 3];

    fn covered(t: &Target) -> usize {
        t.inv_depth.iter().filter(|&&z| z > 0.0).count()
    }

    #[test]
    fn triangles_of_either_winding_cover_the_same_pixels() {
        let tri = [[1.0, 1.0, 1.0], [9.0, 2.0, 1.0], [4.0, 8.0, 1.0]];
        let mut a = Target::new(10, 10, [0; 3]);
        a.fill_triangle(tri, WHITE);
        let mut b = Target::new(10, 10, [0; 3]);
        b.fill_triangle([tri[0], tri[2], tri[1]], WHITE);
        assert_eq!(a.inv_depth, b.inv_depth);
        // Area 27.5 px^2: the pixel-centre count is close to it.
        assert!((covered(&a) as f32 - 27.5).abs() < 6.0, "{}", covered(&a));
    }

    #[test]
    fn a_nearer_triangle_wins_whatever_the_order() {
        let far = [[0.0, 0.0, 0.5], [10.0, 0.0, 0.5], [0.0, 10.0, 0.5]];
        let near = far.map(|[x, y, _]| [x, y, 1.0]);
        for order in [[far, near], [near, far]] {
            let mut t = Target::new(4, 4, [0; 3]);
            t.fill_triangle(order[0], if order[0] == near { WHITE } else { [9; 3] });
            t.fill_triangle(order[1], if order[1] == near { WHITE } else { [9; 3] });
            assert_eq!(t.image.get_pixel(0, 0).0, WHITE);
        }
    }

    #[test]
    fn degenerate_huge_and_offscreen_triangles_draw_nothing_and_do_not_panic() {
        let mut t = Target::new(8, 8, [0; 3]);
        t.fill_triangle([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0], [5.0, 5.0, 1.0]], WHITE);
        t.fill_triangle([[-50.0, -50.0, 1.0], [-40.0, -50.0, 1.0], [-45.0, -40.0, 1.0]], WHITE);
        t.fill_triangle([[f32::NAN, 0.0, 1.0], [4.0, 0.0, 1.0], [0.0, 4.0, 1.0]], WHITE);
        assert_eq!(covered(&t), 0);
        t.fill_triangle([[f32::INFINITY, 0.0, 1.0], [0.0, 4.0, 1.0], [0.0, 0.0, 1.0]], WHITE);
        assert_eq!(covered(&t), 0);
        // A huge but finite triangle around the image covers all of it.
        t.fill_triangle([[f32::MAX, 0.0, 1.0], [-f32::MAX, 0.0, 1.0], [0.0, f32::MAX, 1.0]], WHITE);
        assert_eq!(covered(&t), 64);
    }

    #[test]
    fn clipping_keeps_the_part_in_front_of_the_near_plane() {
        let all_in = [[0.0, 0.0, 1.0], [1.0, 0.0, 2.0], [0.0, 1.0, 3.0]];
        assert_eq!(clip_near(all_in).1, 3);
        let all_out = all_in.map(|[x, y, z]| [x, y, -z]);
        assert_eq!(clip_near(all_out).1, 0);
        let (poly, n) = clip_near([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.0, -1.0]]);
        assert_eq!(n, 4);
        assert!(poly.iter().all(|p| p[2] >= NEAR_PLANE - 1e-6));
        let (_, n) = clip_near([[0.0, 0.0, 1.0], [1.0, 0.0, -1.0], [0.0, 0.0, -1.0]]);
        assert_eq!(n, 3);
    }

    #[test]
    fn discs_cover_about_their_area_and_tiny_ones_one_pixel() {
        let mut t = Target::new(20, 20, [0; 3]);
        t.fill_disc([10.0, 10.0, 1.0], 4.0, WHITE);
        assert!((covered(&t) as f32 - 16.0 * std::f32::consts::PI).abs() < 8.0);
        let mut t = Target::new(20, 20, [0; 3]);
        t.fill_disc([3.3, 7.9, 1.0], 0.1, WHITE);
        assert_eq!(covered(&t), 1);
        assert_eq!(t.image.get_pixel(3, 7).0, WHITE);
        t.fill_disc([-5.0, f32::NAN, 1.0], 2.0, WHITE);
        assert_eq!(covered(&t), 1);
    }
}
