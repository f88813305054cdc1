//! Spheres binned into the screen's 16x16 tiles on the GPU ([`GpuTiles`], `shaders/tiles.wgsl`),
//! the twin of `view::bin` (issue 37: the ray caster's and the screen-space renderer's tiles
//! made where their points are, in the frame's encoder). Each sphere's pixel rectangle is the
//! CPU's (`sphere_rect`: the same projection, the same pixel spans), its tiles emitted as
//! (tile, sphere) pairs in sphere order, then sorted by tile with the bin sort's stable radix
//! passes ([`crate::density::bins`]), so that each tile's spheres come in index order as
//! `bin`'s do. Tested equal to `bin` item for item in `tests/gpu.rs`.
//!
//! The pairs' buffer holds a capacity the caller chooses (the host cannot know the number of
//! pairs without the rectangles): pairs past it are left out, in sphere order, and the frame's
//! statistics ([`TileStats`]: the pairs requested, the longest tile, the fragment cost that
//! `bin` refuses above the view's limit) come back a few frames late without a wait
//! ([`GpuTiles::after_submit`], [`GpuTiles::late_stats`]), or at once for offline use
//! ([`GpuTiles::read_stats`]).

use bytemuck::{Pod, Zeroable};

use super::View;
use crate::density::bins::{RawSortParams, dispatch_of};
use crate::gpu::{self, GpuContext, GpuError};

/// The WGSL of the passes: the bin sort's prefix sum and radix passes, and the binning's own.
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/scan.wgsl"),
    include_str!("../../shaders/bin_sort.wgsl"),
    include_str!("../../shaders/tiles.wgsl")
);

/// The binning's `TileParams` (160 bytes, checked against the WGSL in a test).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct RawTileParams {
    pub view: [[f32; 4]; 4],
    pub proj: [[f32; 4]; 4],
    pub size: [f32; 2],
    pub tiles: [u32; 2],
    pub count: u32,
    pub capacity: u32,
    pub sentinel: u32,
    pub stride: u32,
}

const _: () = assert!(std::mem::size_of::<RawTileParams>() == 160);

/// The passes' entry points, in the order [`GpuTiles`] keeps their pipelines.
const ENTRIES: [&str; 9] = [
    "sphere_tiles",
    "count_blocks",
    "scan_blocks",
    "count_starts",
    "emit_pairs",
    "radix_histogram",
    "scan_table",
    "radix_scatter",
    "tile_items",
];
const SPHERE_TILES: usize = 0;
const EMIT: usize = 4;
const RADIX: usize = 5;
const ITEMS: usize = 8;

/// Counts each invocation of the bin sort's prefix sum adds in turn (`RUN` in its WGSL).
const COUNT_RUN: usize = 16;

/// Radix passes at most (8 bits each: a key below 2^32).
const MAX_PASSES: usize = 4;

/// How far two views' matrices may differ for [`GpuTiles::plan`] to take one's statistics for
/// the other's (against each matrix's largest entry).
const NEAR_VIEW: f32 = 0.01;

/// How far each entry of two perspective views' rotations may differ for [`GpuTiles::plan`] to
/// scale one's statistics for the other (about 6 degrees: a camera turning a degree a frame,
/// its statistics back a few frames late).
const NEAR_TURN: f32 = 0.1;

/// The most the pairs of a perspective view's spheres may grow, as estimated, for
/// [`GpuTiles::plan`] to scale a recent view's statistics for it.
const MOST_GROWTH: f64 = 4.0;

/// Spheres per parallel chunk of [`Binned::scaled_perspective`]'s pass.
const SUM_CHUNK: usize = 4096;

/// The views whose latest statistics [`GpuTiles`] keeps for [`GpuTiles::plan`].
const VIEWS_KEPT: usize = 4;

/// The sort's parameter slices: the spheres' prefix sum, the tiles', then one per radix pass.
const SLICES: usize = 2 + MAX_PASSES;

/// What a binning found, read back after its work ran: the pairs it needed (more than the
/// capacity: some were left out), the most spheres in one tile, and the pixel fragments of the
/// spheres' rectangles (the cost `view::check_cost` limits).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TileStats {
    pub requested: u32,
    pub most_in_tile: u32,
    pub fragments: u64,
}

impl TileStats {
    fn of(words: &[u32]) -> Self {
        Self {
            requested: words[0],
            most_in_tile: words[1],
            fragments: u64::from(words[2]) | (u64::from(words[3]) << 32),
        }
    }
}

/// A buffer kept from frame to frame, bound whole.
fn whole(b: &gpu::Grow) -> wgpu::BindingResource<'_> {
    b.buffer().as_entire_binding()
}

/// What makes two binnings alike for [`GpuTiles::plan`]: nearly the same view (its matrices
/// and size), and the spheres and capacity of the binning.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Binned {
    view: [f32; 32],
    size: (u32, u32),
    count: u32,
    capacity: u32,
}

impl Binned {
    fn of(v: &View, count: u32, capacity: u32) -> Self {
        let (view, _, proj) = v.matrices();
        let mut matrices = [0.0; 32];
        matrices[..16].copy_from_slice(&view.to_cols_array());
        matrices[16..].copy_from_slice(&proj.to_cols_array());
        Self {
            view: matrices,
            size: (v.width, v.height),
            count,
            capacity,
        }
    }

    /// Whether `other` looks from nearly the same place: the same size, and each of its two
    /// matrices within [`NEAR_VIEW`] of this one's (each entry's difference against the
    /// matrix's largest entry). The views a frame fits to the particles' box move a little from
    /// frame to frame; the spheres' tiles then change by about as much.
    fn near_view(&self, other: &Self) -> bool {
        let near = |a: &[f32], b: &[f32]| {
            let scale = a.iter().chain(b).fold(0.0f32, |m, x| m.max(x.abs()));
            a.iter()
                .zip(b)
                .all(|(x, y)| (x - y).abs() <= NEAR_VIEW * scale)
        };
        self.size == other.size
            && near(&self.view[..16], &other.view[..16])
            && near(&self.view[16..], &other.view[16..])
    }

    /// How the spheres' tiles may have changed since `then` when both are orthographic views
    /// of the same size looking the same way (each entry of their rotations within
    /// [`NEAR_VIEW`]) whose windows differ: a light's screen fitted to each frame's water, which
    /// moves and resizes with it. Their pixels per world unit differ by `sx` along x and `sy`
    /// along y, so a sphere's rectangle covers at most `max(sx, 1) max(sy, 1)` times as many
    /// tiles (a rectangle of `w` pixels spans `w / 16 + 1` tiles at most), and a tile holds at
    /// most `max(1 / sx, 1) max(1 / sy, 1)` times as many spheres (those of that many tiles of
    /// the view before, for spheres whose rectangle is under a tile; approximately); those two
    /// factors. A window moved across the water changes which tiles a sphere meets, not (beyond
    /// its edges) how many.
    fn scaled_from(&self, then: &Self) -> Option<(f64, f64)> {
        // (an orthographic projection's last row is (0, 0, 0, 1))
        let orthographic = |m: &[f32; 32]| m[16 + 11] == 0.0 && m[16 + 15] == 1.0;
        let rotation = [0, 1, 2, 4, 5, 6, 8, 9, 10];
        let turned = rotation
            .iter()
            .any(|&k| (self.view[k] - then.view[k]).abs() > NEAR_VIEW);
        if self.size != then.size
            || turned
            || !orthographic(&self.view)
            || !orthographic(&then.view)
        {
            return None;
        }
        let ratio =
            |k: usize| f64::from(self.view[16 + k].abs()) / f64::from(then.view[16 + k].abs());
        let (sx, sy) = (ratio(0), ratio(5));
        if !(sx.is_finite() && sy.is_finite() && sx > 0.0 && sy > 0.0) {
            return None;
        }
        Some((
            sx.max(1.0) * sy.max(1.0),
            (1.0 / sx).max(1.0) * (1.0 / sy).max(1.0),
        ))
    }

    /// [`Self::scaled_from`] for two perspective views of the same size (a moving camera: a
    /// game's, a viewer's) whose rotations differ by at most [`NEAR_TURN`] in each entry, for
    /// the `n` spheres (centre and radius of sphere `j`) as they are now: `None` where the two
    /// are not alike so or the change is larger than [`MOST_GROWTH`] (such a frame is
    /// counted). One pass over the spheres estimates, in both views, the tiles and pixels each
    /// sphere's rectangle covers from its centre's depth alone (`f r / z` pixels, `f` the focal
    /// length in pixels; the whole screen for a sphere whose bounding cube reaches behind the
    /// eye, nothing for one wholly behind it or off the screen), far cheaper than the rectangles themselves; the factors are the ratios of
    /// the two views' sums (the pairs', the fragments'), and for the longest tile `1 / s^2`
    /// with `s` the most any sphere seen in both shrank (spheres that shrink crowd into fewer
    /// tiles). Estimates: they follow a camera that turns, comes nearer or pans (which spheres
    /// the screen shows, and how large), not how the spheres regroup into tiles (the caller
    /// adds half again).
    fn scaled_perspective(
        &self,
        then: &Self,
        n: usize,
        sphere: &(impl Fn(usize) -> (glam::Vec3, f32) + Sync),
    ) -> Option<(f64, f64, f64)> {
        use rayon::prelude::*;
        // (a perspective projection's last row is (0, 0, -1, 0))
        let perspective = |m: &[f32; 32]| m[16 + 11] == -1.0 && m[16 + 15] == 0.0;
        let rotation = [0, 1, 2, 4, 5, 6, 8, 9, 10];
        let turned = rotation
            .iter()
            .any(|&k| (self.view[k] - then.view[k]).abs() > NEAR_TURN);
        if self.size != then.size || turned || !perspective(&self.view) || !perspective(&then.view)
        {
            return None;
        }
        let views = [Footprint::of(self), Footprint::of(then)];
        // (in chunks, each summed in a loop of its own: a fold per sphere cost twice as much)
        let sums = (0..n.div_ceil(SUM_CHUNK))
            .into_par_iter()
            .map(|k| {
                let mut sums = ViewSums::default();
                for j in k * SUM_CHUNK..((k + 1) * SUM_CHUNK).min(n) {
                    let (c, r) = sphere(j);
                    sums.add(views[0].of_sphere(c, r), views[1].of_sphere(c, r));
                }
                sums
            })
            .reduce(ViewSums::default, ViewSums::join);
        if !(sums.tiles[1] > 0.0 && sums.pixels[1] > 0.0) {
            return None;
        }
        let pairs = sums.tiles[0] / sums.tiles[1];
        let fragments = sums.pixels[0] / sums.pixels[1];
        if !(pairs <= MOST_GROWTH && fragments.is_finite()) {
            return None;
        }
        let crowd = if sums.least.is_finite() && sums.least > 0.0 {
            (1.0 / sums.least).max(1.0).powi(2)
        } else {
            1.0
        };
        Some((pairs, fragments, crowd))
    }
}

/// A perspective view's mapping of a sphere to the screen as [`Binned::scaled_perspective`]
/// estimates it: its projection times its view matrix, its focal lengths in pixels and its
/// size.
#[derive(Clone, Copy)]
struct Footprint {
    clip: glam::Mat4,
    /// How far a sphere's bounding cube reaches in depth per unit of its radius (the L1 norm of
    /// the view's depth row: its corners' depths lie within `z +- r reach`).
    reach: f32,
    /// Pixels per unit of `x / z` and `y / z`, times two (a sphere's side per unit of `r / z`).
    focal: glam::Vec2,
    size: glam::Vec2,
    /// Tiles per pixel.
    per_tile: f32,
}

/// What [`Footprint::of_sphere`] estimates of one sphere in one view: the tiles and pixels of
/// its rectangle, its side in pixels (0 off the screen; infinite where it reaches the eye).
#[derive(Clone, Copy)]
struct Covered {
    tiles: f32,
    pixels: f32,
    side: f32,
}

impl Covered {
    const NONE: Self = Self {
        tiles: 0.0,
        pixels: 0.0,
        side: 0.0,
    };
}

impl Footprint {
    fn of(b: &Binned) -> Self {
        let view = glam::Mat4::from_cols_slice(&b.view[..16]);
        let proj = glam::Mat4::from_cols_slice(&b.view[16..]);
        let size = glam::Vec2::new(b.size.0 as f32, b.size.1 as f32);
        Self {
            clip: proj * view,
            reach: view.x_axis.z.abs() + view.y_axis.z.abs() + view.z_axis.z.abs(),
            focal: size * glam::Vec2::new(proj.x_axis.x, proj.y_axis.y),
            size,
            per_tile: 1.0 / super::TILE as f32,
        }
    }

    /// The sphere at `c` of radius `r` on this view's screen.
    #[inline]
    fn of_sphere(&self, c: glam::Vec3, r: f32) -> Covered {
        let clip = self.clip * c.extend(1.0);
        // (a perspective projection's w is the depth in front of the eye)
        let z = clip.w;
        if !(r > 0.0 && z.is_finite()) {
            return Covered::NONE;
        }
        // (a conversion to an integer truncates, the floor of a number >= 0, without the
        // call to `floorf` that the x86-64 baseline makes of `floor`)
        let tiles_of = |s: glam::Vec2| {
            let t = (s.min(self.size) * self.per_tile).as_uvec2() + 1;
            (t.x * t.y) as f32
        };
        if z + r * self.reach <= 0.0 {
            // its bounding cube wholly behind the eye: not drawn (`sphere_rect`)
            return Covered::NONE;
        }
        if z - r * self.reach <= 0.0 {
            // its bounding cube reaches behind the eye: the whole screen (`sphere_rect`)
            return Covered {
                tiles: tiles_of(self.size),
                pixels: self.size.x * self.size.y,
                side: f32::INFINITY,
            };
        }
        let centre = (clip.truncate().truncate() / z * 0.5 + 0.5) * self.size;
        let side = r / z * self.focal;
        let half = 0.5 * side;
        if (centre + half).cmplt(glam::Vec2::ZERO).any() || (centre - half).cmpgt(self.size).any() {
            return Covered::NONE;
        }
        let on = side.min(self.size);
        Covered {
            tiles: tiles_of(side),
            pixels: on.x * on.y,
            side: side.y,
        }
    }
}

/// The sums of [`Binned::scaled_perspective`]'s pass: per view (now, then) the tiles and pixels
/// of every sphere, and the smallest ratio of a sphere's side now to its side then over the
/// spheres on both screens.
#[derive(Clone, Copy)]
struct ViewSums {
    tiles: [f64; 2],
    pixels: [f64; 2],
    least: f64,
}

impl Default for ViewSums {
    fn default() -> Self {
        Self {
            tiles: [0.0; 2],
            pixels: [0.0; 2],
            least: f64::INFINITY,
        }
    }
}

impl ViewSums {
    fn add(&mut self, now: Covered, then: Covered) {
        self.tiles[0] += f64::from(now.tiles);
        self.tiles[1] += f64::from(then.tiles);
        self.pixels[0] += f64::from(now.pixels);
        self.pixels[1] += f64::from(then.pixels);
        if now.side > 0.0 && then.side > 0.0 && then.side.is_finite() {
            self.least = self.least.min(f64::from(now.side / then.side));
        }
    }

    fn join(self, other: Self) -> Self {
        Self {
            tiles: [
                self.tiles[0] + other.tiles[0],
                self.tiles[1] + other.tiles[1],
            ],
            pixels: [
                self.pixels[0] + other.pixels[0],
                self.pixels[1] + other.pixels[1],
            ],
            least: self.least.min(other.least),
        }
    }
}

/// The bind groups, one per pass (each pipeline has its own layout, derived from the bindings
/// its entry point uses).
struct Binds {
    sphere_tiles: wgpu::BindGroup,
    /// `count_blocks`, `scan_blocks`, `count_starts` over the spheres' counts, then the tiles'.
    sphere_scan: [wgpu::BindGroup; 3],
    tile_scan: [wgpu::BindGroup; 3],
    emit: wgpu::BindGroup,
    /// Per radix pass: `radix_histogram`, `scan_table`, `radix_scatter`.
    radix: Vec<[wgpu::BindGroup; 3]>,
    /// `tile_items` reading the sorted pairs: after an even number of passes, then an odd one.
    items: [wgpu::BindGroup; 2],
}

/// The binning's passes and buffers, kept from frame to frame (grown when a frame needs more).
pub struct GpuTiles {
    pipelines: [wgpu::ComputePipeline; ENTRIES.len()],
    params: wgpu::Buffer,
    sort_params: wgpu::Buffer,
    stride: u64,
    slots: gpu::Grow,
    rects: gpu::Grow,
    pairs: [gpu::Grow; 2],
    starts: gpu::Grow,
    block_sums: gpu::Grow,
    table: gpu::Grow,
    items: gpu::Grow,
    stats: wgpu::Buffer,
    /// The spheres' buffer the bind groups hold.
    spheres: Option<wgpu::Buffer>,
    binds: Option<Binds>,
    /// The statistics' late read (behind a lock: [`Self::encode`] borrows the binning shared).
    /// (with the binning whose statistics it copied)
    readback: std::sync::Mutex<(gpu::AsyncRead, Option<Binned>)>,
    /// The last [`Self::prepare`]'s binning, and the last whose statistics came back.
    binned: Option<Binned>,
    /// (one per view, the most recent few: a frame may bin for several views, the optics'
    /// light's and the camera's)
    counted: Vec<(Binned, TileStats)>,
    /// Whether the last [`Self::plan`] counted the pairs on the CPU.
    planned_on_cpu: bool,
    /// Spheres, tiles along x, tiles, the pairs' capacity and the radix passes of the last
    /// [`Self::prepare`].
    count: u32,
    tiles_x: u32,
    /// Tiles of the last binning.
    tiles: usize,
    capacity: u32,
    passes: usize,
    created: usize,
}

impl GpuTiles {
    /// Compiles the passes for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        Self::with_pipelines(
            device,
            gpu::compute_pipelines(device, "tiles", SHADER, ENTRIES),
        )
    }

    /// Another binning with buffers of its own, sharing this one's compiled passes.
    #[must_use]
    pub fn sharing(&self, device: &wgpu::Device) -> Self {
        Self::with_pipelines(device, self.pipelines.clone())
    }

    fn with_pipelines(
        device: &wgpu::Device,
        pipelines: [wgpu::ComputePipeline; ENTRIES.len()],
    ) -> Self {
        let stride = (std::mem::size_of::<RawSortParams>() as u64).next_multiple_of(u64::from(
            device.limits().min_uniform_buffer_offset_alignment,
        ));
        let uniform = |label, size| crate::gpu::uniform_buffer(device, label, size);
        // (read back by the tests)
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        Self {
            pipelines,
            params: uniform("tile params", std::mem::size_of::<RawTileParams>() as u64),
            sort_params: uniform("tile sort params", stride * SLICES as u64),
            stride,
            slots: gpu::Grow::new("tile sphere slots", usage),
            rects: gpu::Grow::new("tile rects", usage),
            pairs: [
                gpu::Grow::new("tile pairs", usage),
                gpu::Grow::new("tile pairs", usage),
            ],
            starts: gpu::Grow::new("tile starts", usage),
            block_sums: gpu::Grow::new("tile block sums", usage),
            table: gpu::Grow::new("tile radix table", usage),
            items: gpu::Grow::new("tile items", usage),
            stats: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("tile stats"),
                size: 16,
                usage: usage | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            spheres: None,
            binds: None,
            readback: std::sync::Mutex::new((
                gpu::AsyncRead::new(device, "tile stats readback", 16),
                None,
            )),
            binned: None,
            counted: Vec::new(),
            planned_on_cpu: false,
            count: 0,
            tiles_x: 0,
            tiles: 0,
            capacity: 0,
            passes: 0,
            created: 0,
        }
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough
    /// and the spheres' buffer is the same).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// Where each tile's spheres start in [`Self::items`], one more entry than tiles (the last:
    /// the pairs emitted).
    #[must_use]
    pub fn starts(&self) -> &wgpu::Buffer {
        self.starts.buffer()
    }

    /// The tiles' spheres, tile by tile, each tile's in index order.
    #[must_use]
    pub fn items(&self) -> &wgpu::Buffer {
        self.items.buffer()
    }

    /// Tiles along x of the last binning.
    #[must_use]
    pub fn tiles_x(&self) -> u32 {
        self.tiles_x
    }

    /// Whether the last [`Self::plan`] counted the pairs on the CPU (else it sized them from
    /// a recent binning's statistics).
    #[must_use]
    pub fn planned_on_cpu(&self) -> bool {
        self.planned_on_cpu
    }

    /// The pairs the last binning could hold.
    #[must_use]
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// [`Self::prepare`] then [`Self::encode`]: the binning of `count` spheres (centre and radius
    /// in the first `vec4` of each, `stride` `vec4`s apart in `spheres`) into the 16x16 tiles of
    /// view `v`, with room for `capacity` (tile, sphere) pairs, recorded into `encoder`.
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        v: &View,
        spheres: (&wgpu::Buffer, u32, u32),
        capacity: u32,
    ) -> Result<(), GpuError> {
        self.prepare((&ctx.device, &ctx.queue), v, spheres, capacity)?;
        self.encode(encoder);
        Ok(())
    }

    /// Makes the buffers and bind groups for the binning of `count` spheres (centre and radius
    /// in the first `vec4` of each, `stride` `vec4`s apart in `spheres`) into the 16x16 tiles
    /// of view `v` with room for `capacity` (tile, sphere) pairs, and writes its parameters
    /// through `queue` (one view per submission). Refused when the buffers would exceed the
    /// adapter's storage binding limit.
    pub fn prepare(
        &mut self,
        (device, queue): (&wgpu::Device, &wgpu::Queue),
        v: &View,
        (spheres, count, stride): (&wgpu::Buffer, u32, u32),
        capacity: u32,
    ) -> Result<(), GpuError> {
        let (tw, th) = v.tiles();
        let tiles = tw * th;
        let capacity = capacity.max(1) as usize;
        let n = count as usize;
        let groups = capacity.div_ceil(256);
        let table = 256 * groups;
        let max_binding = gpu::max_binding(device);
        let too_large = [
            capacity as u64 * 8,
            (n as u64 + 1) * 4,
            n as u64 * 16,
            table as u64 * 4,
        ]
        .iter()
        .any(|&b| b > max_binding);
        if too_large || capacity >= 1 << 31 || n >= 1 << 31 || stride == 0 {
            return Err(GpuError::Validation(format!(
                "{n} spheres with room for {capacity} tile pairs exceed the GPU's storage binding limit of {max_binding} bytes"
            )));
        }
        if u64::from(stride) * n as u64 * 16 > spheres.size() {
            return Err(GpuError::Validation(format!(
                "{n} spheres {stride} vec4s apart do not fit a buffer of {} bytes",
                spheres.size()
            )));
        }
        let made = [
            self.slots.reserve(device, (n as u64 + 1) * 4),
            self.rects.reserve(device, n as u64 * 16),
            self.pairs[0].reserve(device, capacity as u64 * 8),
            self.pairs[1].reserve(device, capacity as u64 * 8),
            self.starts.reserve(device, (tiles as u64 + 1) * 4),
            self.block_sums.reserve(
                device,
                (n.max(tiles) + 1).div_ceil(256 * COUNT_RUN) as u64 * 4,
            ),
            self.table.reserve(device, table as u64 * 4),
            self.items.reserve(device, capacity as u64 * 4),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        if self.binds.is_none() || self.created > 0 || self.spheres.as_ref() != Some(spheres) {
            self.spheres = Some(spheres.clone());
            self.binds = Some(self.bind_groups(device, spheres));
            self.created += 1;
        }
        self.tiles_x = tw as u32;
        self.tiles = tiles;
        self.capacity = capacity as u32;
        self.count = count;
        self.binned = Some(Binned::of(v, count, capacity as u32));
        // the radix passes sort the pairs by tile, the sentinel (past every tile) included
        let sentinel = tiles as u32;
        self.passes = (32 - sentinel.leading_zeros()).div_ceil(8) as usize;
        let (view, _, proj) = v.matrices();
        let raw = RawTileParams {
            view: view.to_cols_array_2d(),
            proj: proj.to_cols_array_2d(),
            size: [v.width as f32, v.height as f32],
            tiles: [tw as u32, th as u32],
            count,
            capacity: capacity as u32,
            sentinel,
            stride,
        };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&raw));
        let scan = |entries: usize| RawSortParams {
            entries: entries as u32,
            ..Default::default()
        };
        let mut slices = vec![0u8; self.sort_params.size() as usize];
        let sort = (0..MAX_PASSES).map(|p| RawSortParams {
            count: capacity as u32,
            shift: 8 * p as u32,
            groups: groups as u32,
            entries: table as u32,
            ..Default::default()
        });
        for (s, params) in [scan(n + 1), scan(tiles + 1)]
            .into_iter()
            .chain(sort)
            .enumerate()
        {
            let at = s * self.stride as usize;
            slices[at..at + std::mem::size_of::<RawSortParams>()]
                .copy_from_slice(bytemuck::bytes_of(&params));
        }
        queue.write_buffer(&self.sort_params, 0, &slices);
        Ok(())
    }

    /// Records the binning [`Self::prepare`] made ready into `encoder` (nothing before one).
    pub fn encode(&self, encoder: &mut wgpu::CommandEncoder) {
        let Some(binds) = self.binds.as_ref() else {
            return;
        };
        let (n, tiles, capacity, passes) = (
            self.count as usize,
            self.tiles,
            self.capacity as usize,
            self.passes,
        );
        encoder.clear_buffer(&self.stats, 0, None);
        encoder.clear_buffer(self.starts.buffer(), 0, Some((tiles as u64 + 1) * 4));
        encoder.clear_buffer(self.slots.buffer(), n as u64 * 4, Some(4));
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("tiles"),
            timestamp_writes: None,
        });
        let mut run = |entry: usize, bind: &wgpu::BindGroup, (x, y): (u32, u32)| {
            pass.set_pipeline(&self.pipelines[entry]);
            pass.set_bind_group(0, bind, &[]);
            pass.dispatch_workgroups(x, y, 1);
        };
        let blocks = |items: usize| dispatch_of(items.div_ceil(256) as u32);
        let scan_blocks = |entries: usize| dispatch_of(entries.div_ceil(256 * COUNT_RUN) as u32);
        if n > 0 {
            run(SPHERE_TILES, &binds.sphere_tiles, blocks(n));
        }
        for (k, bind) in binds.sphere_scan.iter().enumerate() {
            let size = if k == 1 { (1, 1) } else { scan_blocks(n + 1) };
            run(1 + k, bind, size);
        }
        run(EMIT, &binds.emit, blocks(capacity));
        for (k, bind) in binds.tile_scan.iter().enumerate() {
            let size = if k == 1 {
                (1, 1)
            } else {
                scan_blocks(tiles + 1)
            };
            run(1 + k, bind, size);
        }
        for radix in &binds.radix[..passes] {
            run(RADIX, &radix[0], blocks(capacity));
            run(RADIX + 1, &radix[1], (1, 1));
            run(RADIX + 2, &radix[2], blocks(capacity));
        }
        run(ITEMS, &binds.items[passes % 2], blocks(capacity.max(tiles)));
        drop(pass);
        if let Ok(mut r) = self.readback.lock()
            && r.0.copy(encoder, &self.stats, 0)
        {
            r.1 = self.binned;
        }
    }

    /// The bind groups over the kept buffers and `spheres`.
    fn bind_groups(&self, device: &wgpu::Device, spheres: &wgpu::Buffer) -> Binds {
        let p = &self.pipelines;
        let slice = |s: usize| {
            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &self.sort_params,
                offset: s as u64 * self.stride,
                size: wgpu::BufferSize::new(std::mem::size_of::<RawSortParams>() as u64),
            })
        };
        let group = |entry: usize, entries: &[(u32, wgpu::BindingResource<'_>)]| {
            gpu::bind_group(device, &p[entry], entries)
        };
        // the prefix sum's three passes over `counts` with the parameters of slice `s`
        let scan = |s: usize, counts: &gpu::Grow| {
            [
                group(
                    1,
                    &[
                        (0, slice(s)),
                        (4, whole(counts)),
                        (5, whole(&self.block_sums)),
                    ],
                ),
                group(2, &[(0, slice(s)), (5, whole(&self.block_sums))]),
                group(
                    3,
                    &[
                        (0, slice(s)),
                        (4, whole(counts)),
                        (5, whole(&self.block_sums)),
                    ],
                ),
            ]
        };
        let radix = (0..MAX_PASSES)
            .map(|pass| {
                let (from, to) = (&self.pairs[pass % 2], &self.pairs[1 - pass % 2]);
                let s = 2 + pass;
                [
                    group(
                        RADIX,
                        &[(0, slice(s)), (2, whole(from)), (7, whole(&self.table))],
                    ),
                    group(RADIX + 1, &[(0, slice(s)), (7, whole(&self.table))]),
                    group(
                        RADIX + 2,
                        &[
                            (0, slice(s)),
                            (2, whole(from)),
                            (3, whole(to)),
                            (7, whole(&self.table)),
                        ],
                    ),
                ]
            })
            .collect();
        let items = |sorted: &gpu::Grow| {
            group(
                ITEMS,
                &[
                    (8, self.params.as_entire_binding()),
                    (2, whole(sorted)),
                    (4, whole(&self.starts)),
                    (10, whole(&self.slots)),
                    (12, whole(&self.items)),
                    (13, self.stats.as_entire_binding()),
                ],
            )
        };
        Binds {
            sphere_tiles: group(
                SPHERE_TILES,
                &[
                    (8, self.params.as_entire_binding()),
                    (9, spheres.as_entire_binding()),
                    (10, whole(&self.slots)),
                    (11, whole(&self.rects)),
                    (13, self.stats.as_entire_binding()),
                ],
            ),
            sphere_scan: scan(0, &self.slots),
            tile_scan: scan(1, &self.starts),
            emit: group(
                EMIT,
                &[
                    (8, self.params.as_entire_binding()),
                    (2, whole(&self.pairs[0])),
                    (4, whole(&self.starts)),
                    (10, whole(&self.slots)),
                    (11, whole(&self.rects)),
                ],
            ),
            radix,
            items: [items(&self.pairs[0]), items(&self.pairs[1])],
        }
    }

    /// Forgets the statistics of the binnings so far, those on their way back included: the
    /// next [`Self::plan`] counts on the CPU. For a caller whose next lists are of another kind
    /// than the last (other spheres in a like number), whose statistics would size them wrong.
    pub fn forget(&mut self) {
        self.counted.clear();
        if let Ok(r) = self.readback.get_mut() {
            r.1 = None;
        }
    }

    /// Starts the mapping of the statistics' copy once the encoder [`Self::record`] wrote into
    /// is submitted.
    pub fn after_submit(&mut self) {
        if let Ok(r) = self.readback.get_mut() {
            r.0.after_submit();
        }
    }

    /// The statistics of a recent binning, once its read has come back (a few frames late; no
    /// wait), else `None`.
    pub fn late_stats(&mut self) -> Option<TileStats> {
        let (read, binned) = self.readback.get_mut().ok()?;
        let stats = TileStats::of(bytemuck::cast_slice(&read.take()?));
        if let Some(b) = binned.take() {
            self.counted.retain(|(c, _)| !c.near_view(&b));
            if self.counted.len() == VIEWS_KEPT {
                self.counted.remove(0);
            }
            self.counted.push((b, stats));
        }
        Some(stats)
    }

    /// The room to make for binning the `n` spheres (centre and radius of sphere `j`) in view
    /// `v` ([`Self::prepare`]'s capacity) and the most spheres one tile will hold, without a
    /// wait: from the statistics of a recent binning that came back ([`Self::late_stats`],
    /// taken here) where that binning is like this one (nearly the same view: the same size,
    /// the matrices within 1 % of their largest entry; every pair fitted, at most a quarter
    /// more spheres: its pairs scaled by the spheres' growth, the room kept while they stay a
    /// quarter under it, else half as much again) or where its view is an orthographic one of
    /// the same size looking the same way with another window (a light's screen fitted to each
    /// frame's water: its pairs and longest tile scaled by the spheres' growth and by how the
    /// pixel's size changed, `Binned::scaled_from`, with half again as much room and for the
    /// longest tile) or a perspective one of the same size turned by a few degrees at most (a
    /// moving camera: scaled alike by how the spheres' tiles and pixels change between the two
    /// views, estimated in one pass over the spheres from their centres' depths,
    /// `Binned::scaled_perspective`: 0.19-0.32 ms for the dam break's 24,389 spheres on this
    /// 2-core machine, where counting them takes 1.3-1.9 ms); otherwise counted on the CPU
    /// ([`super::tile_counts`], refused as `view::bin` refuses: the first frame and a camera's
    /// cut pay this, the rectangles without the lists), with a quarter more room. A like frame
    /// whose spheres spread over more tiles than that room leaves the pairs past it out (in
    /// sphere order) until its statistics come back, a few frames later: the next frame is
    /// counted then.
    pub fn plan(
        &mut self,
        v: &View,
        n: usize,
        sphere: impl Fn(usize) -> (glam::Vec3, f32) + Sync,
    ) -> Result<(u32, usize), super::SplatError> {
        self.late_stats();
        let now = Binned::of(v, n as u32, 0);
        if let Some((then, stats)) = self.counted.iter().find(|(c, _)| c.near_view(&now))
            && stats.requested <= then.capacity
            && stats.fragments <= v.max_fragments
            && (n as u64) * 4 <= u64::from(then.count.max(1)) * 5
        {
            let growth = (n as f64 / f64::from(then.count.max(1))).max(1.0);
            let needed = (f64::from(stats.requested) * growth).ceil() as u64;
            let most = (f64::from(stats.most_in_tile) * growth).ceil() as usize;
            let room = if needed + needed / 4 > u64::from(then.capacity) {
                needed + needed / 2
            } else {
                u64::from(then.capacity)
            };
            self.planned_on_cpu = false;
            return Ok((room.min(u64::from(u32::MAX)) as u32, most));
        }
        // a like orthographic view (pairs and fragments scaled alike), else a perspective
        // one whose spheres are counted cheaply
        let scaled = |c: &Binned| {
            now.scaled_from(c)
                .map(|(area, crowd)| (area, area, crowd))
                .or_else(|| now.scaled_perspective(c, n, &sphere))
        };
        if let Some((then, stats, (area, fragments_grow, crowd))) = self
            .counted
            .iter()
            .rev()
            .find_map(|(c, s)| scaled(c).map(|f| (c, s, f)))
            && stats.requested <= then.capacity
            // (a binning of no sphere, or of none on its screen, scales to no room: the empty
            // frame before a lone drop's)
            && stats.requested > 0
            && (n as u64) * 4 <= u64::from(then.count) * 5
        {
            let growth = (n as f64 / f64::from(then.count.max(1))).max(1.0);
            let fragments = stats.fragments as f64 * growth * fragments_grow;
            if fragments <= v.max_fragments as f64 {
                let needed = (f64::from(stats.requested) * growth * area).ceil();
                let room = (needed * 1.5).ceil().min(f64::from(u32::MAX)) as u32;
                // (an estimate: a window moved by part of a tile regroups the spheres into
                // tiles, measured up to 16 % more in the longest; half again)
                let most = (stats.most_in_tile as f64 * growth * crowd * 1.5).ceil() as usize;
                self.planned_on_cpu = false;
                return Ok((room, most));
            }
        }
        self.planned_on_cpu = true;
        let (pairs, most) = super::tile_counts(v, n, sphere)?;
        // a quarter more: the next like frame keeps this room while its pairs stay under it
        Ok(((pairs + pairs / 4).min(u64::from(u32::MAX)) as u32, most))
    }

    /// The statistics of the last binning, read back at once (a wait: tests and offline use).
    pub fn read_stats(&self, ctx: &GpuContext) -> Result<TileStats, GpuError> {
        let words: Vec<u32> = gpu::read_buffer(ctx, &self.stats)?;
        Ok(TileStats::of(&words))
    }

    /// The last binning read back as `view::bin` gives it (tiles along x, each tile's
    /// spheres): a wait, for tests and offline use.
    pub fn read(&self, ctx: &GpuContext) -> Result<(usize, Vec<Vec<u32>>), GpuError> {
        let starts: Vec<u32> = gpu::read_buffer(ctx, self.starts())?;
        let items: Vec<u32> = gpu::read_buffer(ctx, self.items())?;
        let tiles = (0..self.tiles)
            .map(|t| items[starts[t] as usize..starts[t + 1] as usize].to_vec())
            .collect();
        Ok((self.tiles_x as usize, tiles))
    }
}
