//! Measures of a picture's quality that the tests, the `render --json` report and the benches
//! share: holes inside a silhouette, isolated dark specks, and the mean difference of two frames.
//!
//! These turn what one sees when opening a PNG into numbers:
//! - [`holes`]: background showing through inside the surface. The silhouette is *closed*
//!   (dilated, then eroded, by a square of half-width `radius` pixels), which fills every gap
//!   narrower than about `2 radius` pixels; the holes are the uncovered pixels of the closed
//!   silhouette. A gap between two separate parts of the water wider than that is not a hole.
//!   [`Holes::enclosed`] counts only those that the border cannot reach through the background:
//!   in spray, the closing also fills the gaps between neighbouring drops, which are no holes.
//! - [`specks`]: pixels much darker than their neighbourhood (below `ratio` times the median
//!   luminance of the `window x window` square around them): the 1-pixel dark dots of a badly
//!   normalised splat or a shadow test that fails on one texel.
//! - [`mean_abs_diff`]: the mean absolute difference of two images' RGB values, in [0, 1].
//!
//! And one measure of a surface: [`MeshDistance`], the exact distance from points to a triangle
//! mesh (our surfels against a peer's marching-cubes mesh).

use glam::Vec3;
use image::RgbaImage;

use crate::view::Render;

/// Holes inside a silhouette, from [`holes`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Holes {
    /// Pixels of the closed silhouette.
    pub silhouette: usize,
    /// Pixels of the closed silhouette that the mask does not cover.
    pub holes: usize,
    /// Those of `holes` that the image border cannot reach through uncovered pixels
    /// (4-connected): pinholes and cracks of a surface, without the gaps between spray drops
    /// that the closing fills but that open to the outside.
    pub enclosed: usize,
}

impl Holes {
    /// Holes as a fraction of the closed silhouette (0 for an empty one).
    #[must_use]
    pub fn fraction(&self) -> f64 {
        self.holes as f64 / self.silhouette.max(1) as f64
    }

    /// Enclosed holes as a fraction of the closed silhouette.
    #[must_use]
    pub fn enclosed_fraction(&self) -> f64 {
        self.enclosed as f64 / self.silhouette.max(1) as f64
    }
}

/// Running maximum (`dilate`) or minimum of a boolean line over a window of half-width `r`;
/// outside the line counts as `outside`.
fn line_filter(src: &[bool], dst: &mut [bool], r: usize, dilate: bool, outside: bool) {
    let n = src.len();
    // prefix counts of set values make each window O(1)
    let mut prefix = Vec::with_capacity(n + 1);
    prefix.push(0usize);
    for &v in src {
        prefix.push(prefix.last().copied().unwrap_or(0) + usize::from(v));
    }
    for (i, d) in dst.iter_mut().enumerate() {
        let lo = i.saturating_sub(r);
        let hi = (i + r + 1).min(n);
        let set = prefix[hi] - prefix[lo];
        let cut = (i < r) || (i + r + 1 > n);
        *d = if dilate {
            set > 0 || (cut && outside)
        } else {
            set == hi - lo && (!cut || outside)
        };
    }
}

/// Dilation (`dilate`) or erosion of a `width x height` mask by a square of half-width `r`,
/// separably (rows, then columns).
fn morph(mask: &[bool], width: usize, height: usize, r: usize, dilate: bool) -> Vec<bool> {
    // dilation: nothing outside the image; erosion: the outside counts as covered, so the
    // closing contains the mask everywhere, borders included
    let outside = !dilate;
    let mut rows = vec![false; mask.len()];
    for y in 0..height {
        let s = y * width..(y + 1) * width;
        line_filter(&mask[s.clone()], &mut rows[s], r, dilate, outside);
    }
    let mut out = vec![false; mask.len()];
    let (mut col, mut res) = (vec![false; height], vec![false; height]);
    for x in 0..width {
        for y in 0..height {
            col[y] = rows[y * width + x];
        }
        line_filter(&col, &mut res, r, dilate, outside);
        for y in 0..height {
            out[y * width + x] = res[y];
        }
    }
    out
}

/// Morphological closing of a `width x height` mask (row-major) by a square of half-width
/// `radius` pixels: dilation, then erosion. Contains the mask.
///
/// # Panics
/// When `mask.len() != width * height`.
#[must_use]
pub fn closing(mask: &[bool], width: usize, height: usize, radius: usize) -> Vec<bool> {
    assert_eq!(mask.len(), width * height, "mask of the wrong size");
    let dilated = morph(mask, width, height, radius, true);
    morph(&dilated, width, height, radius, false)
}

/// Holes of a coverage mask: the pixels inside its closing by `radius` pixels that it does not
/// cover (see the module's documentation).
///
/// # Panics
/// When `mask.len() != width * height`.
#[must_use]
pub fn holes(mask: &[bool], width: usize, height: usize, radius: usize) -> Holes {
    let closed = closing(mask, width, height, radius);
    let silhouette = closed.iter().filter(|&&c| c).count();
    let holes = closed.iter().zip(mask).filter(|&(&c, &m)| c && !m).count();
    let outside = reachable_from_border(mask, width, height);
    let enclosed = (0..mask.len())
        .filter(|&i| closed[i] && !mask[i] && !outside[i])
        .count();
    Holes {
        silhouette,
        holes,
        enclosed,
    }
}

/// The uncovered pixels that the image border reaches through uncovered pixels (4-connected).
pub(crate) fn reachable_from_border(mask: &[bool], w: usize, h: usize) -> Vec<bool> {
    let mut outside = vec![false; w * h];
    let mut stack: Vec<usize> = (0..w * h)
        .filter(|&i| {
            let (x, y) = (i % w, i / w);
            (x == 0 || y == 0 || x + 1 == w || y + 1 == h) && !mask[i]
        })
        .collect();
    for &i in &stack {
        outside[i] = true;
    }
    while let Some(i) = stack.pop() {
        let (x, y) = (i % w, i / w);
        let near = [
            (x > 0).then(|| i - 1),
            (x + 1 < w).then(|| i + 1),
            (y > 0).then(|| i - w),
            (y + 1 < h).then(|| i + w),
        ];
        for j in near.into_iter().flatten() {
            if !outside[j] && !mask[j] {
                outside[j] = true;
                stack.push(j);
            }
        }
    }
    outside
}

/// `image` with the holes of `mask` (see [`holes`]) painted, to look at where they are: enclosed
/// ones magenta, the others (open to the border, such as gaps between drops) cyan.
///
/// # Panics
/// When `mask` is not one value per pixel of `image`.
#[must_use]
pub fn mark_holes(image: &RgbaImage, mask: &[bool], radius: usize) -> RgbaImage {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let closed = closing(mask, w, h, radius);
    let outside = reachable_from_border(mask, w, h);
    let mut out = image.clone();
    for (i, p) in out.pixels_mut().enumerate() {
        if closed[i] && !mask[i] {
            *p = if outside[i] {
                image::Rgba([0, 255, 255, 255])
            } else {
                image::Rgba([255, 0, 255, 255])
            };
        }
    }
    out
}

/// The pixels of `image` that differ from `background` (RGB exactly): the silhouette of what
/// was drawn on a flat background.
#[must_use]
pub fn coverage_on(image: &RgbaImage, background: [u8; 3]) -> Vec<bool> {
    image.pixels().map(|p| p.0[..3] != background[..]).collect()
}

/// Rec. 709 luminance of an 8-bit RGB pixel, in [0, 255].
fn luma(p: &image::Rgba<u8>) -> f32 {
    0.2126 * f32::from(p[0]) + 0.7152 * f32::from(p[1]) + 0.0722 * f32::from(p[2])
}

/// Pixels darker than `ratio` times the median luminance of the `window x window` square
/// around them (the square clipped at the borders). `window` is odd, 3 or more.
///
/// # Panics
/// When `window` is even or below 3.
#[must_use]
pub fn specks(image: &RgbaImage, window: u32, ratio: f32) -> usize {
    speck_mask(image, window, ratio)
        .iter()
        .filter(|&&s| s)
        .count()
}

/// The pixels of `mask` (`width x height`, row-major) none of whose 8 neighbours is set: of a
/// [`speck_mask`], the 1-pixel dots, without the thin dark lines (a shadow's edge, a wall's
/// seam seen through the water) whose pixels the speck test flags too.
///
/// # Panics
/// When `mask.len() != width * height`.
#[must_use]
pub fn isolated(mask: &[bool], width: usize, height: usize) -> usize {
    assert_eq!(mask.len(), width * height, "mask of the wrong size");
    (0..mask.len())
        .filter(|&i| {
            let (x, y) = ((i % width) as i64, (i / width) as i64);
            mask[i]
                && (-1..=1i64).all(|dy| {
                    (-1..=1i64).all(|dx| {
                        let (xx, yy) = (x + dx, y + dy);
                        (dx == 0 && dy == 0)
                            || xx < 0
                            || yy < 0
                            || xx >= width as i64
                            || yy >= height as i64
                            || !mask[yy as usize * width + xx as usize]
                    })
                })
        })
        .count()
}

/// The pixels [`specks`] counts, row-major.
///
/// # Panics
/// When `window` is even or below 3.
#[must_use]
pub fn speck_mask(image: &RgbaImage, window: u32, ratio: f32) -> Vec<bool> {
    assert!(
        window >= 3 && window % 2 == 1,
        "window must be odd and >= 3"
    );
    let (w, h) = (image.width() as usize, image.height() as usize);
    let lum: Vec<f32> = image.pixels().map(luma).collect();
    let r = (window / 2) as usize;
    let mut values = Vec::with_capacity((window * window) as usize);
    let mut mask = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            values.clear();
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                values.extend_from_slice(
                    &lum[yy * w + x.saturating_sub(r)..yy * w + (x + r + 1).min(w)],
                );
            }
            let mid = values.len() / 2;
            let (_, median, _) = values.select_nth_unstable_by(mid, f32::total_cmp);
            mask[y * w + x] = lum[y * w + x] < ratio * *median;
        }
    }
    mask
}

/// Mean absolute difference of the RGB values of two images of one size, in [0, 1].
///
/// # Panics
/// When the sizes differ.
#[must_use]
pub fn mean_abs_diff(a: &RgbaImage, b: &RgbaImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions(), "images of different sizes");
    let (mut sum, mut n) = (0u64, 0u64);
    for (p, q) in a.pixels().zip(b.pixels()) {
        for c in 0..3 {
            sum += u64::from(p[c].abs_diff(q[c]));
            n += 1;
        }
    }
    sum as f64 / (255.0 * n.max(1) as f64)
}

/// How far a render's surface lies from a reference render of the same view ([`against`]):
/// depth and normal errors over the pixels both cover, and where they cover differently.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SurfaceDifference {
    /// Pixels both cover.
    pub both: usize,
    /// Pixels only the render covers.
    pub only_render: usize,
    /// Pixels only the reference covers.
    pub only_reference: usize,
    /// `(only_render + only_reference) / reference's covered pixels`.
    pub coverage_difference: f64,
    /// Mean and 95th percentile of the distance along the pixel's ray between the two surfaces,
    /// in units of `unit` (world units divided by it; a particle spacing, say).
    pub depth_mean: f64,
    pub depth_p95: f64,
    /// Mean and 95th percentile of the angle between the two normals, in degrees.
    pub normal_mean_degrees: f64,
    pub normal_p95_degrees: f64,
}

/// Compares `render` with `reference`, both drawn in `view` (their buffers' depths are view
/// depths along the pixel's ray, as every renderer here writes them): depth differences are
/// measured along the world ray and divided by `unit`.
///
/// # Panics
/// When the two renders or the view differ in size.
#[must_use]
pub fn against(
    render: &Render,
    reference: &Render,
    view: &crate::view::View,
    unit: f32,
) -> SurfaceDifference {
    assert_eq!(
        (render.width, render.height),
        (reference.width, reference.height),
        "renders of different sizes"
    );
    assert_eq!((view.width, view.height), (render.width, render.height));
    let w = render.width as usize;
    let (mut depths, mut angles) = (Vec::new(), Vec::new());
    let mut d = SurfaceDifference::default();
    for i in 0..render.colour.len() {
        match (render.depth(i), reference.depth(i)) {
            (Some(a), Some(b)) => {
                let pixel = glam::Vec2::new((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                let length = view.world_ray(pixel).1.length();
                depths.push(f64::from((a - b).abs() * length / unit));
                if let (Some(n), Some(m)) = (render.normal(i), reference.normal(i)) {
                    angles.push(f64::from(n.dot(m).clamp(-1.0, 1.0).acos().to_degrees()));
                }
            }
            (Some(_), None) => d.only_render += 1,
            (None, Some(_)) => d.only_reference += 1,
            (None, None) => {}
        }
    }
    d.both = depths.len();
    d.coverage_difference =
        (d.only_render + d.only_reference) as f64 / (d.both + d.only_reference).max(1) as f64;
    let stats = |v: &mut Vec<f64>| {
        if v.is_empty() {
            return (0.0, 0.0);
        }
        v.sort_by(f64::total_cmp);
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let p95 = v[((v.len() - 1) as f64 * 0.95).round() as usize];
        (mean, p95)
    };
    (d.depth_mean, d.depth_p95) = stats(&mut depths);
    (d.normal_mean_degrees, d.normal_p95_degrees) = stats(&mut angles);
    d
}

/// Distance from `p` to the triangle `abc` (Ericson, Real-Time Collision Detection, §5.1.5: the
/// closest point by Voronoi regions of the vertices, edges and face).
#[must_use]
pub fn point_triangle_distance(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> f32 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return ap.length();
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return bp.length();
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return (p - (a + ab * (d1 / (d1 - d3)))).length();
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return cp.length();
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return (p - (a + ac * (d2 / (d2 - d6)))).length();
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (p - (b + (c - b) * w)).length();
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    (p - (a + ab * v + ac * w)).length()
}

/// Most cells along one axis of a [`MeshDistance`] grid.
const MESH_GRID_AXIS: usize = 256;
/// Most (cell, triangle) entries of a [`MeshDistance`] grid: a coarser grid is used beyond it.
const MESH_GRID_ENTRIES: usize = 1 << 26;

/// Exact distances from points to a triangle mesh (how far one surface lies from another, e.g.
/// our surfels from a peer's marching-cubes mesh). The triangles are binned by their bounding
/// boxes into a uniform grid; a query searches shells of cells around its own, one ring at a
/// time, and stops once no unseen triangle can be nearer than the nearest found (every unseen
/// triangle lies outside the searched cube, at least the distance to its nearest inner face).
/// The result is the brute-force minimum over all triangles, bit for bit.
#[derive(Clone, Debug)]
pub struct MeshDistance {
    triangles: Vec<[Vec3; 3]>,
    origin: Vec3,
    cell: f32,
    dims: [usize; 3],
    /// `start[c]..start[c + 1]` of `items`: the triangles whose box meets cell `c`
    start: Vec<u32>,
    items: Vec<u32>,
    /// what the rounding of cell coordinates may move a box face by, kept off the stopping bound
    slack: f32,
}

impl MeshDistance {
    /// The grid over `triangles`, with cells of about `cell` (coarsened so that there are at
    /// most 256 along an axis and 2^26 entries). Non-finite vertices are left out, with their
    /// triangles.
    #[must_use]
    pub fn new(triangles: Vec<[Vec3; 3]>, cell: f32) -> Self {
        let triangles: Vec<[Vec3; 3]> = triangles
            .into_iter()
            .filter(|t| t.iter().all(|v| v.is_finite()))
            .collect();
        let (lo, hi) = triangles
            .iter()
            .flatten()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        if triangles.is_empty() {
            return Self {
                triangles,
                origin: Vec3::ZERO,
                cell: 1.0,
                dims: [1; 3],
                start: vec![0, 0],
                items: Vec::new(),
                slack: 0.0,
            };
        }
        let extent = (hi - lo).max_element();
        let mut cell = if cell.is_finite() && cell > 0.0 {
            cell
        } else {
            extent
        };
        cell = cell
            .max(extent / MESH_GRID_AXIS as f32)
            .max(f32::MIN_POSITIVE);
        loop {
            let dims = ((hi - lo) / cell)
                .to_array()
                .map(|d| (d as usize + 1).min(MESH_GRID_AXIS + 1));
            let grid = Self {
                triangles: Vec::new(),
                origin: lo,
                cell,
                dims,
                start: Vec::new(),
                items: Vec::new(),
                slack: cell * 1e-3 + (lo.abs().max(hi.abs()).max_element() + extent) * 1e-6,
            };
            let entries: usize = triangles
                .iter()
                .map(|t| {
                    let (a, b) = grid.cell_box(t);
                    (0..3).map(|i| b[i] - a[i] + 1).product::<usize>()
                })
                .sum();
            if entries > MESH_GRID_ENTRIES && cell < extent {
                cell *= 2.0;
                continue;
            }
            return grid.fill(triangles);
        }
    }

    fn cell_of(&self, p: Vec3) -> [usize; 3] {
        let c = ((p - self.origin) / self.cell).max(Vec3::ZERO).to_array();
        [0, 1, 2].map(|i| (c[i] as usize).min(self.dims[i] - 1))
    }

    /// The cells a triangle's bounding box meets, inclusive.
    fn cell_box(&self, t: &[Vec3; 3]) -> ([usize; 3], [usize; 3]) {
        let lo = t[0].min(t[1]).min(t[2]);
        let hi = t[0].max(t[1]).max(t[2]);
        (self.cell_of(lo), self.cell_of(hi))
    }

    fn key(&self, c: [usize; 3]) -> usize {
        c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])
    }

    fn fill(mut self, triangles: Vec<[Vec3; 3]>) -> Self {
        let cells = self.dims.iter().product::<usize>();
        let mut start = vec![0u32; cells + 1];
        let each = |grid: &Self, f: &mut dyn FnMut(usize, u32)| {
            for (i, t) in triangles.iter().enumerate() {
                let (a, b) = grid.cell_box(t);
                for z in a[2]..=b[2] {
                    for y in a[1]..=b[1] {
                        for x in a[0]..=b[0] {
                            f(grid.key([x, y, z]), i as u32);
                        }
                    }
                }
            }
        };
        each(&self, &mut |k, _| start[k + 1] += 1);
        for k in 0..cells {
            start[k + 1] += start[k];
        }
        let mut next = start[..cells].to_vec();
        let mut items = vec![0u32; start[cells] as usize];
        each(&self, &mut |k, i| {
            items[next[k] as usize] = i;
            next[k] += 1;
        });
        self.start = start;
        self.items = items;
        self.triangles = triangles;
        self
    }

    /// Distance from `p` to the nearest triangle; infinite for a mesh without triangles or a
    /// non-finite `p`.
    #[must_use]
    pub fn distance(&self, p: Vec3) -> f32 {
        if self.triangles.is_empty() || !p.is_finite() {
            return f32::INFINITY;
        }
        let c = self.cell_of(p);
        let mut best = f32::INFINITY;
        let near = |key: usize| {
            self.items[self.start[key] as usize..self.start[key + 1] as usize]
                .iter()
                .map(|&t| {
                    let [a, b, cc] = self.triangles[t as usize];
                    point_triangle_distance(p, a, b, cc)
                })
                .fold(f32::INFINITY, f32::min)
        };
        // cells visited; past the triangle count a brute-force pass is the cheaper exact answer
        // (a point far from a finely gridded mesh)
        let mut cells = 0usize;
        for k in 0..=self.dims.iter().copied().max().unwrap_or(1) {
            let lo = [0, 1, 2].map(|i| c[i].saturating_sub(k));
            let hi = [0, 1, 2].map(|i| (c[i] + k).min(self.dims[i] - 1));
            // the shell of cells `k` from `c` (those nearer were searched in earlier rings)
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    if z.abs_diff(c[2]) == k || y.abs_diff(c[1]) == k {
                        for x in lo[0]..=hi[0] {
                            best = best.min(near(self.key([x, y, z])));
                        }
                        cells += hi[0] - lo[0] + 1;
                    } else {
                        if c[0] >= k {
                            best = best.min(near(self.key([c[0] - k, y, z])));
                        }
                        if k > 0 && c[0] + k < self.dims[0] {
                            best = best.min(near(self.key([c[0] + k, y, z])));
                        }
                        cells += 2;
                    }
                }
            }
            // the unseen triangles lie in cells outside the cube lo..=hi: at least as far as
            // its nearest face that is not the grid's border
            let mut bound = f32::INFINITY;
            for i in 0..3 {
                if lo[i] > 0 {
                    bound = bound.min(p[i] - (self.origin[i] + lo[i] as f32 * self.cell));
                }
                if hi[i] + 1 < self.dims[i] {
                    bound = bound.min(self.origin[i] + (hi[i] + 1) as f32 * self.cell - p[i]);
                }
            }
            if best <= bound - self.slack {
                break;
            }
            if cells > self.triangles.len() {
                return self
                    .triangles
                    .iter()
                    .map(|t| point_triangle_distance(p, t[0], t[1], t[2]))
                    .fold(f32::INFINITY, f32::min);
            }
        }
        best
    }

    /// [`Self::distance`] of every point, in parallel.
    #[must_use]
    pub fn distances(&self, points: &[Vec3]) -> Vec<f32> {
        use rayon::prelude::*;
        points.par_iter().map(|&p| self.distance(p)).collect()
    }
}

/// Peak signal-to-noise ratio of two images' RGB channels in dB (infinite when equal).
///
/// # Panics
/// When the sizes differ.
#[must_use]
pub fn psnr(a: &RgbaImage, b: &RgbaImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions(), "images of different sizes");
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (p, q) in a.pixels().zip(b.pixels()) {
        for c in 0..3 {
            let d = f64::from(p[c]) - f64::from(q[c]);
            sum += d * d;
            n += 1;
        }
    }
    let mse = sum / n.max(1) as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}

/// The absolute difference of two images, scaled by `gain`, for failure reports.
#[must_use]
pub fn difference_image(a: &RgbaImage, b: &RgbaImage, gain: u8) -> RgbaImage {
    RgbaImage::from_fn(a.width(), a.height(), |x, y| {
        let (p, q) = (a.get_pixel(x, y), b.get_pixel(x, y));
        let d = |c: usize| p[c].abs_diff(q[c]).saturating_mul(gain);
        image::Rgba([d(0), d(1), d(2), 255])
    })
}

/// Holes of a render: uncovered pixels that cannot be reached from the image border through
/// uncovered pixels (4-connected), i.e. background showing through inside the silhouette.
#[must_use]
pub fn enclosed_holes(render: &Render) -> usize {
    let covered: Vec<bool> = render.colour.iter().map(|c| c[3] > 0.0).collect();
    let outside = reachable_from_border(&covered, render.width as usize, render.height as usize);
    covered
        .iter()
        .zip(&outside)
        .filter(|&(&c, &o)| !c && !o)
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed mesh: the 12 triangles of the cube `[lo, hi]`.
    fn cube(lo: Vec3, hi: Vec3) -> Vec<[Vec3; 3]> {
        let v = |i: usize| {
            Vec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            )
        };
        let faces = [
            [0, 1, 3, 2],
            [4, 6, 7, 5],
            [0, 4, 5, 1],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 5, 7, 3],
        ];
        faces
            .iter()
            .flat_map(|f| [[v(f[0]), v(f[1]), v(f[2])], [v(f[0]), v(f[2]), v(f[3])]])
            .collect()
    }

    #[test]
    fn point_triangle_distance_in_each_region() {
        let (a, b, c) = (Vec3::ZERO, Vec3::X, Vec3::Y);
        // above the face, beyond an edge, beyond a vertex
        assert_eq!(
            point_triangle_distance(Vec3::new(0.25, 0.25, 2.0), a, b, c),
            2.0
        );
        assert_eq!(
            point_triangle_distance(Vec3::new(0.5, -3.0, 0.0), a, b, c),
            3.0
        );
        assert_eq!(
            point_triangle_distance(Vec3::new(-3.0, -4.0, 0.0), a, b, c),
            5.0
        );
        let d = point_triangle_distance(Vec3::new(1.0, 1.0, 0.0), a, b, c);
        assert!((d - 0.5f32.sqrt()).abs() < 1e-6, "{d}");
    }

    /// The grid search gives the brute-force minimum, bit for bit: points inside, near and far
    /// from a mesh of two cubes and a thin sliver, with cells from much finer than the
    /// triangles to coarser than the mesh.
    #[test]
    fn mesh_distance_equals_brute_force() {
        let mut tris = cube(Vec3::ZERO, Vec3::ONE);
        tris.extend(cube(Vec3::new(3.0, 0.5, -1.0), Vec3::new(3.2, 2.5, 0.3)));
        tris.push([
            Vec3::new(-1.0, -1.0, 2.0),
            Vec3::new(4.0, -0.9, 2.1),
            Vec3::new(-0.9, 3.0, 2.0),
        ]);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let points: Vec<Vec3> = (0..2000)
            .map(|_| Vec3::new(rnd(), rnd(), rnd()) * 12.0 - Vec3::splat(4.0))
            .collect();
        for cell in [0.01, 0.1, 0.37, 1.0, 50.0] {
            let mesh = MeshDistance::new(tris.clone(), cell);
            let fast = mesh.distances(&points);
            for (p, d) in points.iter().zip(&fast) {
                let brute = tris
                    .iter()
                    .map(|t| point_triangle_distance(*p, t[0], t[1], t[2]))
                    .fold(f32::INFINITY, f32::min);
                assert_eq!(d.to_bits(), brute.to_bits(), "cell {cell}, point {p}");
            }
        }
        // a point on a face, an empty mesh, a non-finite point, non-finite vertices
        let mesh = MeshDistance::new(tris.clone(), 0.2);
        assert_eq!(mesh.distance(Vec3::new(0.5, 0.5, 0.0)), 0.0);
        assert_eq!(
            MeshDistance::new(Vec::new(), 0.1).distance(Vec3::ZERO),
            f32::INFINITY
        );
        assert_eq!(mesh.distance(Vec3::NAN), f32::INFINITY);
        let mut bad = tris;
        bad.push([Vec3::NAN, Vec3::ZERO, Vec3::ONE]);
        assert_eq!(
            MeshDistance::new(bad, 0.2).distance(Vec3::new(0.5, 0.5, -1.0)),
            1.0
        );
    }

    fn disk(w: usize, h: usize, c: (f32, f32), r: f32) -> Vec<bool> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                (x - c.0).powi(2) + (y - c.1).powi(2) <= r * r
            })
            .collect()
    }

    #[test]
    fn against_measures_depth_along_the_ray_normals_and_coverage() {
        use crate::view::{Camera, Light, Render, SplatParams, View};
        let (w, h) = (8u32, 6u32);
        let view = View::new(
            &Camera::default(),
            &Light::default(),
            &SplatParams::default(),
            w,
            h,
        )
        .unwrap();
        let n = (w * h) as usize;
        // the reference: every pixel at depth 2 facing +z; the render: depth 2.5, normal tilted
        // 90 degrees on half the pixels, and two pixels missing
        let reference = Render {
            width: w,
            height: h,
            image: image::RgbaImage::new(w, h),
            colour: vec![[0.0, 0.0, 0.0, 1.0]; n],
            normal_depth: vec![[0.0, 0.0, 1.0, 2.0]; n],
        };
        let mut render = reference.clone();
        for i in 0..n {
            render.normal_depth[i][3] = 2.5;
            if i % 2 == 0 {
                render.normal_depth[i] = [1.0, 0.0, 0.0, 2.5];
            }
        }
        render.colour[1] = [0.0; 4];
        render.colour[3] = [0.0; 4];
        let d = against(&render, &reference, &view, 0.5);
        assert_eq!((d.both, d.only_render, d.only_reference), (n - 2, 0, 2));
        assert!((d.coverage_difference - 2.0 / n as f64).abs() < 1e-12);
        // 0.5 of view depth is at least 0.5 of distance along each ray, 1 unit of 0.5
        assert!(d.depth_mean >= 1.0 && d.depth_mean < 1.2, "{d:?}");
        // the covered pixels: 24 tilted (even indices), 22 untilted
        let mean = 90.0 * 24.0 / 46.0;
        assert!((d.normal_mean_degrees - mean).abs() < 1e-3, "{d:?}");
        assert!((d.normal_p95_degrees - 90.0).abs() < 1e-3, "{d:?}");
    }

    #[test]
    fn closing_contains_the_mask_and_keeps_a_convex_shape() {
        let (w, h) = (40, 30);
        // a disk touching the border: closing neither loses nor (much) grows it
        let m = disk(w, h, (5.0, 15.0), 9.0);
        let c = closing(&m, w, h, 3);
        assert!(m.iter().zip(&c).all(|(&a, &b)| !a || b));
        let grown = c.iter().zip(&m).filter(|&(&c, &m)| c && !m).count();
        assert!(grown <= 8, "closing grew a disk by {grown} pixels");
        assert_eq!(holes(&m, w, h, 3).holes, grown);
    }

    #[test]
    fn holes_count_pinholes_and_narrow_cracks_not_wide_gaps() {
        let (w, h) = (60, 40);
        let mut m = vec![false; w * h];
        // two filled rectangles 12 px apart: the gap between them is no hole
        for y in 5..35 {
            for x in 5..25 {
                m[y * w + x] = true;
            }
            for x in 37..55 {
                m[y * w + x] = true;
            }
        }
        assert_eq!(holes(&m, w, h, 3).holes, 0);
        // a 3-px notch in the first one's edge: a hole of the closed silhouette, not enclosed
        for y in 20..23 {
            m[y * w + 5] = false;
        }
        let notch = holes(&m, w, h, 3);
        assert_eq!((notch.holes, notch.enclosed), (3, 0));
        for y in 20..23 {
            m[y * w + 5] = true;
        }
        // three pinholes and a 2-px crack of 10 px in the first one
        for &(x, y) in &[(10, 10), (15, 20), (20, 30)] {
            m[y * w + x] = false;
        }
        for y in 12..22 {
            for x in 12..14 {
                m[y * w + x] = false;
            }
        }
        let hl = holes(&m, w, h, 3);
        assert_eq!(hl.holes, 3 + 20);
        assert_eq!(hl.enclosed, 3 + 20);
        assert_eq!(hl.silhouette, 30 * 20 + 30 * 18);
        assert!((hl.fraction() - 23.0 / 1140.0).abs() < 1e-12);
    }

    #[test]
    fn specks_find_dark_dots_on_smooth_gradients_only() {
        let mut img = RgbaImage::from_fn(50, 40, |x, _| {
            let v = (60 + 3 * x) as u8;
            image::Rgba([v, v, v, 255])
        });
        assert_eq!(specks(&img, 7, 0.6), 0);
        img.put_pixel(10, 10, image::Rgba([20, 20, 20, 255]));
        img.put_pixel(30, 30, image::Rgba([100, 100, 100, 255])); // darker, not by 0.6x
        img.put_pixel(0, 0, image::Rgba([0, 0, 0, 255])); // at a corner
        assert_eq!(specks(&img, 7, 0.6), 2);
        // a dark line is specks, not isolated ones; the dot is
        for x in 20..30 {
            img.put_pixel(x, 5, image::Rgba([10, 10, 10, 255]));
        }
        let mask = speck_mask(&img, 7, 0.6);
        assert_eq!(mask.iter().filter(|&&m| m).count(), 12);
        assert_eq!(isolated(&mask, 50, 40), 2);
    }

    #[test]
    fn mean_abs_diff_is_in_unit_range() {
        let a = RgbaImage::from_pixel(4, 4, image::Rgba([0, 0, 0, 255]));
        let b = RgbaImage::from_pixel(4, 4, image::Rgba([255, 255, 255, 0]));
        assert_eq!(mean_abs_diff(&a, &a), 0.0);
        assert_eq!(mean_abs_diff(&a, &b), 1.0);
        let mut c = a.clone();
        c.put_pixel(0, 0, image::Rgba([51, 0, 0, 255]));
        assert!((mean_abs_diff(&a, &c) - 0.2 / 48.0).abs() < 1e-12);
    }
}
