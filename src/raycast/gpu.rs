//! Ray casting on the GPU: `shaders/raycast.wgsl` (compute passes: the cast and the normals as a
//! resumable state machine run until every pixel is done, band of rows by band of rows, then the
//! bilateral filter) over the points, their screen tiles (binned on the GPU before the cast,
//! [`GpuTiles`], equal to the CPU's) and two uniform grids in storage buffers; the shading after the read-back is the CPU's (`splat::shade`). The CPU reference
//! ([`super::cpu`]) is the specification; tests compare the two.

use glam::Vec3;
use wgpu::util::DeviceExt;

use super::{Caster, RayCast, RayCastError, RayNormals};
use crate::density::{Kernel, Points};
use crate::gpu::{GpuContext, GpuError};
use crate::splat::{Camera, Light, Render, SplatParams, View};
use crate::view::gpu::GpuTiles;

/// The WGSL source of the passes.
pub const SHADER: &str = concat!(
    include_str!("../../shaders/eigen.wgsl"),
    include_str!("../../shaders/raycast.wgsl")
);

/// Most cells all grids together may have (32 MiB of starts); a wider spread of points gets
/// coarser cells (still correct: a query visits the 27 cells about it, each at least one reach
/// wide).
const MAX_CELLS: u64 = 1 << 23;

/// Most grids: 32 radius groups (the density's, [`crate::surfels::ExactDensity::groups`], merged
/// in pairs while there are more) and the PCA grid (`MAX_GRIDS` in the WGSL).
pub const MAX_GRIDS: usize = 33;

/// One grid (`Grid` in the WGSL): origin and cell; cells along x, y, z and the offset of their
/// starts in the cells buffer; the offset of their items.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawGrid {
    pub g: [f32; 4],
    pub dims: [u32; 4],
    pub at: [u32; 4],
}

/// Every grid (`Grids` in the WGSL).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawGrids {
    pub grid: [RawGrid; MAX_GRIDS],
}

/// The uniforms of the passes (`Params` in the WGSL, 208 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawCastParams {
    pub inv_view: [[f32; 4]; 4],
    pub screen: [f32; 4],
    pub a: [u32; 4],
    pub b: [f32; 4],
    pub c: [u32; 4],
    pub d: [f32; 4],
    pub e: [f32; 4],
    pub g: [u32; 4],
    /// the water's colour before the tint (rgb) and its absorption per world length (rgb)
    pub base: [f32; 4],
    pub absorb: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<RawCastParams>() == 208);

/// The band of rows one run of `cs_step` works on (`Band` in the WGSL): its first row and rows,
/// the loop iterations of a run, its workgroups.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawBand {
    pub y0: u32,
    pub rows: u32,
    pub budget: u32,
    pub groups_x: u32,
    pub groups_y: u32,
    pub _pad0: u32,
    pub _pad1: u32,
    pub _pad2: u32,
}

/// Bytes of a pixel's `State` in the WGSL (five `vec4`s).
const STATE_BYTES: u64 = 80;

/// Most pixels of one band: their states take 20 MiB.
const BAND_PIXELS: u32 = 1 << 18;

/// Loop iterations of one dispatch of `cs_step`, the same for every pixel: well under the
/// 65,535 that llvmpipe allows all loops of an invocation together (see the WGSL's header),
/// with room for the Jacobi sweeps of the pixels that finish their PCA normal.
const BUDGET: u32 = 16_384;

/// Points sorted into cubic cells (compressed rows: `starts[c]..starts[c + 1]` index `items`).
struct CsrGrid {
    origin: Vec3,
    cell: f32,
    dims: [u32; 3],
    starts: Vec<u32>,
    items: Vec<u32>,
}

/// The dimensions of a grid of cells `cell` wide over `lo..=hi`.
fn grid_dims(lo: Vec3, hi: Vec3, cell: f32) -> [u64; 3] {
    let n = ((hi - lo) / cell).floor() + Vec3::ONE;
    [n.x as u64, n.y as u64, n.z as u64]
}

/// The bounds of some points.
fn bounds_of(points: &Points<'_>, members: &[u32]) -> (Vec3, Vec3) {
    members
        .iter()
        .map(|&j| points.positions[j as usize])
        .fold(None, |b: Option<(Vec3, Vec3)>, p| {
            Some(b.map_or((p, p), |(a, c)| (a.min(p), c.max(p))))
        })
        .unwrap_or((Vec3::ZERO, Vec3::ZERO))
}

/// The points `members` in cells `cell` wide over their bounds `lo..`, the cell of a point (and
/// of a query, in the WGSL) `floor((p - lo) / cell)` clamped to the grid; items are point
/// indices.
fn csr_grid(points: &Points<'_>, members: &[u32], lo: Vec3, cell: f32, dims: [u64; 3]) -> CsrGrid {
    let dims = dims.map(|d| d as u32);
    let cell_of = |p: Vec3| {
        let c = ((p - lo) / cell).floor();
        let at = |k: usize, v: f32| (v.max(0.0) as u32).min(dims[k] - 1);
        at(0, c.x) + dims[0] * (at(1, c.y) + dims[1] * at(2, c.z))
    };
    let total = dims.iter().map(|&d| d as usize).product::<usize>();
    let cells: Vec<u32> = members
        .iter()
        .map(|&j| cell_of(points.positions[j as usize]))
        .collect();
    let mut starts = vec![0u32; total + 1];
    for &c in &cells {
        starts[c as usize + 1] += 1;
    }
    for k in 0..total {
        starts[k + 1] += starts[k];
    }
    let mut fill = starts.clone();
    let mut items = vec![0u32; cells.len()];
    for (&j, &c) in members.iter().zip(&cells) {
        items[fill[c as usize] as usize] = j;
        fill[c as usize] += 1;
    }
    CsrGrid {
        origin: lo,
        cell,
        dims,
        starts,
        items,
    }
}

/// The grids of the density's radius groups (merged in pairs down to `MAX_GRIDS - 1`) and,
/// last, the PCA grid of reach `pca_reach` over all points; cells grow by a common factor until
/// all grids together have at most [`MAX_CELLS`].
fn grids_of(caster: &Caster<'_>, pca_reach: f32) -> Vec<CsrGrid> {
    let points = caster.points();
    let mut groups: Vec<(f32, Vec<u32>)> = caster
        .groups()
        .into_iter()
        .map(|(reach, members)| (reach, members.to_vec()))
        .collect();
    while groups.len() > MAX_GRIDS - 1 {
        groups = groups
            .chunks(2)
            .map(|pair| {
                let reach = pair.iter().map(|g| g.0).fold(0.0, f32::max);
                (
                    reach,
                    pair.iter().flat_map(|g| g.1.iter().copied()).collect(),
                )
            })
            .collect();
    }
    groups.push((pca_reach, (0..points.len() as u32).collect()));
    let bounds: Vec<(Vec3, Vec3)> = groups.iter().map(|g| bounds_of(points, &g.1)).collect();
    let mut scale = 1.0f32;
    let cells = |scale: f32| -> Vec<(f32, [u64; 3])> {
        groups
            .iter()
            .zip(&bounds)
            .map(|((reach, _), &(lo, hi))| {
                let cell = (reach * scale).max(f32::MIN_POSITIVE);
                (cell, grid_dims(lo, hi, cell))
            })
            .collect()
    };
    let mut sizes = cells(scale);
    while sizes
        .iter()
        .map(|(_, d)| d.iter().product::<u64>())
        .sum::<u64>()
        > MAX_CELLS
    {
        scale *= 1.26;
        sizes = cells(scale);
    }
    groups
        .iter()
        .zip(&bounds)
        .zip(sizes)
        .map(|(((_, members), &(lo, _)), (cell, dims))| csr_grid(points, members, lo, cell, dims))
        .collect()
}

impl CsrGrid {
    /// Most points any query visits: the 27 cells about it, at most 27 of the fullest cell.
    fn most_visited(&self) -> u64 {
        let fullest = self
            .starts
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or(0);
        27 * u64::from(fullest)
    }
}

/// What the cast of every view reads of one [`Caster`], the same whatever the view: made by the
/// first view's upload and kept in the caster, so that a frame's views (the light's and the
/// camera's) convert the points and build the grids once (the grids 1.5-2 ms a view on the
/// column's splash frame, this project's machine).
pub(super) struct CastInputs {
    /// Each point's centre and radius.
    points: Vec<[f32; 4]>,
    /// Each point's weight (empty: they are on the GPU, [`Caster::gpu_weights`]).
    weights: Vec<f32>,
    /// Every grid's starts, then their items ([`pack_grids`]), and the grids' uniforms.
    cells: Vec<u32>,
    grids: RawGrids,
    /// How many grids (the PCA's last).
    count: usize,
    /// The points' largest radius and the PCA's reach.
    reach: (f32, f32),
    /// [`iteration_bound`]: a view adds its longest tile's spheres.
    iterations: u64,
}

impl CastInputs {
    fn of(caster: &Caster<'_>) -> Self {
        let points = caster.points();
        let (reach, pca_reach) = (points.max_radius(), caster.pca_reach);
        let grids = grids_of(caster, pca_reach);
        let (cells, raw_grids) = pack_grids(&grids);
        let weights = match caster.gpu_weights() {
            Some(_) => Vec::new(),
            None => (0..points.len()).map(|j| points.weight(j)).collect(),
        };
        Self {
            points: (0..points.len())
                .map(|j| points.positions[j].extend(points.radius(j)).to_array())
                .collect(),
            weights,
            cells,
            grids: raw_grids,
            count: grids.len(),
            reach: (reach, pca_reach),
            iterations: iteration_bound(caster, &grids, caster.params.step * points.min_radius()),
        }
    }
}

/// One frame's inputs on the device: what the bind groups hold, and the runs to record.
struct Frame {
    view: View,
    bands: Vec<Band>,
    filter: wgpu::BindGroup,
    /// Runs of `cs_step` recorded per band: enough for the slowest pixel (an upper bound on the
    /// iterations any pixel needs over [`BUDGET`]); the runs after the last pixel is done
    /// dispatch no workgroups (`cs_args`).
    runs: u64,
}

/// The inputs' buffers, kept from view to view: the uniforms, the points, the tiles, the
/// grids' cells, the weights (grown when a view needs more), and the bands' uniforms (fixed by
/// the size) with their workgroups.
struct Inputs {
    uniforms: wgpu::Buffer,
    grid_uniforms: wgpu::Buffer,
    points: crate::gpu::Grow,
    /// The points' screen tiles, binned on the GPU.
    tiles: GpuTiles,
    cells: crate::gpu::Grow,
    weights: crate::gpu::Grow,
    bands: Vec<(wgpu::Buffer, (u32, u32))>,
}

impl Inputs {
    fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let uniform = |label, size: usize| crate::gpu::uniform_buffer(device, label, size as u64);
        let band_rows = band_rows(width);
        let group_x = width.div_ceil(8);
        let mut bands = Vec::new();
        let mut y0 = 0;
        while y0 < height {
            let rows = band_rows.min(height - y0);
            let groups = (group_x, rows.div_ceil(8));
            let band = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("raycast band"),
                contents: bytemuck::bytes_of(&RawBand {
                    y0,
                    rows,
                    budget: BUDGET,
                    groups_x: groups.0,
                    groups_y: groups.1,
                    _pad0: 0,
                    _pad1: 0,
                    _pad2: 0,
                }),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            bands.push((band, groups));
            y0 += rows;
        }
        let storage = wgpu::BufferUsages::STORAGE;
        Self {
            uniforms: uniform("raycast params", std::mem::size_of::<RawCastParams>()),
            grid_uniforms: uniform("raycast grids", std::mem::size_of::<RawGrids>()),
            points: crate::gpu::Grow::new("raycast points", storage),
            tiles: GpuTiles::new(device),
            cells: crate::gpu::Grow::new("raycast cells", storage),
            weights: crate::gpu::Grow::new("raycast weights", storage),
            bands,
        }
    }
}

struct Band {
    init: wgpu::BindGroup,
    args: wgpu::BindGroup,
    step: wgpu::BindGroup,
    groups: (u32, u32),
}

/// The ray caster's passes on one device at one size, recorded into the caller's encoder: the
/// cast and the normals (`cs_init`, then `cs_args` and an indirect `cs_step` per run, band by
/// band), then the bilateral filter, which writes the water's colour and its normal and depth
/// into two `Rgba32Float` textures, one sample per covered pixel, as the splats' accumulation
/// targets hold them ([`Self::accumulation`]; the GPU optics read them so).
pub struct GpuCaster {
    width: u32,
    height: u32,
    init: wgpu::ComputePipeline,
    args: wgpu::ComputePipeline,
    step: wgpu::ComputePipeline,
    filter: wgpu::ComputePipeline,
    state: wgpu::Buffer,
    unfinished: wgpu::Buffer,
    indirect: wgpu::Buffer,
    hits: wgpu::Buffer,
    extra: wgpu::Buffer,
    colour: wgpu::Texture,
    normal_depth: wgpu::Texture,
    views: (wgpu::TextureView, wgpu::TextureView),
    inputs: Inputs,
    created: usize,
    /// The weights buffer the bind groups read: the uploaded one, or the caster's own on the
    /// GPU ([`Caster::with_gpu_weights`]).
    weights_bound: Option<wgpu::Buffer>,
    frame: Option<Frame>,
}

impl GpuCaster {
    /// The passes and the per-pixel buffers for `width` x `height`.
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Result<Self, GpuError> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("raycast"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let pipeline = |entry| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let buffer = |label, size: u64, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(16),
                usage,
                mapped_at_creation: false,
            })
        };
        let pixels = u64::from(width) * u64::from(height);
        let band_rows = band_rows(width);
        let storage = wgpu::BufferUsages::STORAGE;
        let read = storage | wgpu::BufferUsages::COPY_SRC;
        let texture = |label| {
            crate::gpu::texture_2d(
                device,
                label,
                (width.max(1), height.max(1)),
                wgpu::TextureFormat::Rgba32Float,
                wgpu::TextureUsages::STORAGE_BINDING
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
            )
        };
        let (colour, normal_depth) = (
            texture("raycast colour"),
            texture("raycast normal and depth"),
        );
        let views = (
            colour.create_view(&Default::default()),
            normal_depth.create_view(&Default::default()),
        );
        let caster = Self {
            width,
            height,
            init: pipeline("cs_init"),
            args: pipeline("cs_args"),
            step: pipeline("cs_step"),
            filter: pipeline("cs_filter"),
            state: buffer(
                "raycast state",
                STATE_BYTES
                    * u64::from(width)
                    * u64::from(band_rows.min(height.next_multiple_of(16))),
                storage,
            ),
            unfinished: buffer("raycast unfinished", 4, read),
            indirect: buffer("raycast runs", 12, storage | wgpu::BufferUsages::INDIRECT),
            hits: buffer("raycast hits", 16 * pixels, storage),
            extra: buffer("raycast entries", 16 * pixels, read),
            colour,
            normal_depth,
            views,
            inputs: Inputs::new(device, width, height),
            created: 0,
            weights_bound: None,
            frame: None,
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()));
        }
        Ok(caster)
    }

    /// The size the passes were made for.
    #[must_use]
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The colour (`(tint, 1)`) and normal-depth (`(normal, view depth)`) textures the filter
    /// writes, zero where no ray hits: what [`crate::splat::gpu::SplatRenderer::accumulation`]
    /// holds for the splats.
    #[must_use]
    pub fn accumulation(&self) -> (&wgpu::TextureView, &wgpu::TextureView) {
        (&self.views.0, &self.views.1)
    }

    /// Uploads the caster's points and the grids, for the next [`Self::encode`] (which bins the
    /// points into the screen's tiles of `view` on the GPU, in room planned here by
    /// [`GpuTiles::plan`]), through `queue` into buffers kept from view to view (grown when a view
    /// needs more; the bind groups made anew only then, [`Self::created`]). `view` must have
    /// this caster's size.
    pub fn prepare(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        caster: &Caster<'_>,
        view: &View,
    ) -> Result<(), crate::Error> {
        if (view.width, view.height) != (self.width, self.height) {
            return Err(GpuError::Validation(format!(
                "a {}x{} view for a ray caster made for {}x{}",
                view.width, view.height, self.width, self.height
            ))
            .into());
        }
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.upload(device, queue, caster, view)?;
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        Ok(())
    }

    /// Buffers and bind groups the last [`Self::prepare`] made (0 in the steady state of a
    /// sequence: the inputs written into the kept buffers).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    fn upload(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        caster: &Caster<'_>,
        v: &View,
    ) -> Result<(), crate::Error> {
        let points = caster.points();
        // the tiles' room, from a recent binning of nearly this view or counted here (refused
        // as the CPU's binning refuses), and the longest tile (scaled from a recent binning:
        // half as much again for the run bound, which must not fall short)
        let (room, most_in_tile) = self
            .inputs
            .tiles
            .plan(v, points.len(), |j| (points.positions[j], points.radius(j)))
            .map_err(RayCastError::from)?;
        let most_in_tile = if self.inputs.tiles.planned_on_cpu() {
            most_in_tile
        } else {
            most_in_tile + most_in_tile / 2
        };
        let tw = v.tiles().0;
        // each point's factor on its term (the boundary calibration's weights; 1 without),
        // uploaded, or read where they were solved on the GPU
        let given = caster.gpu_weights();
        if let Some(w) = given
            && w.size() < points.len() as u64 * 4
        {
            return Err(GpuError::Validation(format!(
                "{} bytes of weights on the GPU for {} points",
                w.size(),
                points.len()
            ))
            .into());
        }
        let cast = caster.gpu_inputs.get_or_init(|| CastInputs::of(caster));
        let raw = raw_params(caster, v, tw, cast.reach, cast.count);
        let inputs = &mut self.inputs;
        queue.write_buffer(&inputs.uniforms, 0, bytemuck::bytes_of(&raw));
        queue.write_buffer(&inputs.grid_uniforms, 0, bytemuck::bytes_of(&cast.grids));
        self.created = crate::gpu::write_grown(
            device,
            queue,
            [
                (&mut inputs.points, bytemuck::cast_slice(&cast.points)),
                (&mut inputs.cells, bytemuck::cast_slice(&cast.cells)),
                (&mut inputs.weights, bytemuck::cast_slice(&cast.weights)),
            ],
        );
        inputs.tiles.prepare(
            (device, queue),
            v,
            (inputs.points.buffer(), points.len() as u32, 1),
            room,
        )?;
        self.created += inputs.tiles.created();
        let bound = given.unwrap_or(inputs.weights.buffer());
        if self.weights_bound.as_ref() != Some(bound) {
            // the bind groups read another weights buffer
            self.weights_bound = Some(bound.clone());
            self.created += 1;
        }
        let most = cast.iterations + most_in_tile as u64;
        let runs = most.div_ceil(u64::from(BUDGET)) + 1;
        match &mut self.frame {
            Some(frame) if self.created == 0 => {
                frame.view = *v;
                frame.runs = runs;
            }
            _ => {
                self.frame = Some(self.bind_groups(device, *v, runs));
                self.created += 1;
            }
        }
        Ok(())
    }

    /// The bind groups of the kept buffers, for a frame of `runs` runs seen in `v`.
    fn bind_groups(&self, device: &wgpu::Device, v: View, runs: u64) -> Frame {
        let bind = |pipeline: &wgpu::ComputePipeline,
                    entries: &[(u32, wgpu::BindingResource<'_>)]| {
            let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
                .iter()
                .map(|(binding, resource)| wgpu::BindGroupEntry {
                    binding: *binding,
                    resource: resource.clone(),
                })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("raycast"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            })
        };
        let i = &self.inputs;
        let bands = i
            .bands
            .iter()
            .map(|(band, groups)| Band {
                init: bind(
                    &self.init,
                    &[
                        (0, whole(&i.uniforms)),
                        (2, whole(i.tiles.starts())),
                        (6, whole(&self.hits)),
                        (7, whole(&self.extra)),
                        (9, whole(&self.state)),
                        (10, whole(band)),
                        (11, whole(&self.unfinished)),
                    ],
                ),
                args: bind(
                    &self.args,
                    &[
                        (10, whole(band)),
                        (11, whole(&self.unfinished)),
                        (13, whole(&self.indirect)),
                    ],
                ),
                step: bind(
                    &self.step,
                    &[
                        (0, whole(&i.uniforms)),
                        (1, whole(i.points.buffer())),
                        (3, whole(i.tiles.items())),
                        (4, whole(i.cells.buffer())),
                        (6, whole(&self.hits)),
                        (7, whole(&self.extra)),
                        (9, whole(&self.state)),
                        (10, whole(band)),
                        (11, whole(&self.unfinished)),
                        (12, whole(&i.grid_uniforms)),
                        (
                            16,
                            whole(self.weights_bound.as_ref().expect("set by upload")),
                        ),
                    ],
                ),
                groups: *groups,
            })
            .collect();
        let filter = bind(
            &self.filter,
            &[
                (0, whole(&i.uniforms)),
                (6, whole(&self.hits)),
                (7, whole(&self.extra)),
                (14, wgpu::BindingResource::TextureView(&self.views.0)),
                (15, wgpu::BindingResource::TextureView(&self.views.1)),
            ],
        );
        Frame {
            view: v,
            bands,
            filter,
            runs,
        }
    }

    /// Starts the late read of the tiles' statistics ([`GpuTiles::plan`]) once the encoder
    /// [`Self::encode`] recorded into is submitted.
    pub fn after_submit(&mut self) {
        self.inputs.tiles.after_submit();
    }

    /// Records the cast of the prepared frame into `encoder`: the colour and normal-depth
    /// textures hold it once the encoder has run.
    pub fn encode(&self, encoder: &mut wgpu::CommandEncoder) -> Result<(), GpuError> {
        let frame = self
            .frame
            .as_ref()
            .ok_or_else(|| GpuError::Validation("the ray caster has no prepared frame".into()))?;
        self.inputs.tiles.encode(encoder);
        for band in &frame.bands {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("raycast"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.init);
            pass.set_bind_group(0, &band.init, &[]);
            pass.dispatch_workgroups(band.groups.0, band.groups.1, 1);
            for _ in 0..frame.runs {
                pass.set_pipeline(&self.args);
                pass.set_bind_group(0, &band.args, &[]);
                pass.dispatch_workgroups(1, 1, 1);
                pass.set_pipeline(&self.step);
                pass.set_bind_group(0, &band.step, &[]);
                pass.dispatch_workgroups_indirect(&self.indirect, 0);
            }
        }
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&self.filter);
        pass.set_bind_group(0, &frame.filter, &[]);
        pass.dispatch_workgroups(self.width.div_ceil(8), self.height.div_ceil(8), 1);
        Ok(())
    }

    /// Reads the cast back after its encoder ran: the shaded image (the CPU's shading), the
    /// thickness, entries and the density samples taken.
    pub fn read(&self, ctx: &GpuContext) -> Result<RayCast, GpuError> {
        let frame = self
            .frame
            .as_ref()
            .ok_or_else(|| GpuError::Validation("the ray caster has no prepared frame".into()))?;
        let texels = |t: &wgpu::Texture| -> Result<Vec<[f32; 4]>, GpuError> {
            let bytes = crate::gpu::read_texture(ctx, t, 16)?;
            Ok(bytemuck::pod_collect_to_vec(&bytes))
        };
        let colour = texels(&self.colour)?;
        let normal_depth = texels(&self.normal_depth)?;
        let extra: Vec<[f32; 4]> = crate::gpu::read_buffer(ctx, &self.extra)?;
        let image = crate::splat::cpu::shade_image(&colour, &normal_depth, &frame.view);
        Ok(RayCast {
            render: Render {
                width: self.width,
                height: self.height,
                image,
                colour,
                normal_depth,
            },
            thickness: extra.iter().map(|e| e[1]).collect(),
            entry: extra
                .iter()
                .map(|e| if e[0] < 0.0 { f32::INFINITY } else { e[0] })
                .collect(),
            samples: extra.iter().map(|e| e[2] as u64).sum(),
        })
    }
}

/// The whole of a buffer as a binding.
fn whole(buffer: &wgpu::Buffer) -> wgpu::BindingResource<'_> {
    buffer.as_entire_binding()
}

/// Rows of a band for images `width` wide: a multiple of 16 (whole tiles), at most
/// [`BAND_PIXELS`] pixels when the width allows.
fn band_rows(width: u32) -> u32 {
    (BAND_PIXELS / width.max(1)).max(16) / 16 * 16
}

/// Ray casting of the caster's points on the GPU, as [`super::render_cpu`].
pub fn render_gpu(
    ctx: &GpuContext,
    caster: &Caster<'_>,
    camera: &Camera,
    light: &Light,
    splat: &SplatParams,
    width: u32,
    height: u32,
) -> Result<RayCast, crate::Error> {
    let v = View::new(camera, light, splat, width, height)?;
    render_view_gpu(ctx, caster, &v)
}

/// [`render_gpu`] for a prepared view.
pub fn render_view_gpu(
    ctx: &GpuContext,
    caster: &Caster<'_>,
    v: &View,
) -> Result<RayCast, crate::Error> {
    let mut gpu = GpuCaster::new(&ctx.device, v.width, v.height)?;
    gpu.prepare(&ctx.device, &ctx.queue, caster, v)?;
    let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    gpu.encode(&mut encoder)?;
    ctx.queue.submit([encoder.finish()]);
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()).into());
    }
    Ok(gpu.read(ctx)?)
}

/// Every grid's starts, then every grid's items, in one buffer, and the grids' uniforms that
/// point into it.
fn pack_grids(grids: &[CsrGrid]) -> (Vec<u32>, RawGrids) {
    let mut cells: Vec<u32> = Vec::new();
    let mut raw_grids = RawGrids {
        grid: [RawGrid::default(); MAX_GRIDS],
    };
    for (g, raw) in grids.iter().zip(&mut raw_grids.grid) {
        raw.g = g.origin.extend(g.cell).to_array();
        raw.dims = [g.dims[0], g.dims[1], g.dims[2], cells.len() as u32];
        cells.extend_from_slice(&g.starts);
    }
    for (g, raw) in grids.iter().zip(&mut raw_grids.grid) {
        raw.at = [cells.len() as u32, 0, 0, 0];
        cells.extend_from_slice(&g.items);
    }
    (cells, raw_grids)
}

/// The cast's uniforms for the view `v` (`tw` tiles across), the points' largest radius and the
/// PCA's reach, and `grids` grids (the PCA's last).
fn raw_params(
    caster: &Caster<'_>,
    v: &View,
    tw: usize,
    (reach, pca_reach): (f32, f32),
    grids: usize,
) -> RawCastParams {
    let points = caster.points();
    let params = &caster.params;
    let (_, inv_view, _) = v.matrices();
    let half = v.half_extent();
    let absorb = Vec3::from(params.absorption) / points.h;
    RawCastParams {
        inv_view: inv_view.to_cols_array_2d(),
        screen: [v.width as f32, v.height as f32, half.x, half.y],
        a: [u32::from(v.is_orthographic()), tw as u32, v.width, v.height],
        b: [
            caster.iso(),
            params.step * points.min_radius(),
            points.h,
            params.pca_radius,
        ],
        c: [
            params.bisection_steps,
            match params.normals {
                RayNormals::Blended => 0,
                RayNormals::Gradient => 1,
                RayNormals::Pca => 2,
            },
            match caster.kernel() {
                Kernel::Wyvill => 0,
                Kernel::CubicSpline => 1,
            },
            params.bilateral_radius_px,
        ],
        d: [
            params.blend_d,
            params.blend_k,
            params.blend_max,
            params.bilateral_sigma_px,
        ],
        e: [
            params.bilateral_sigma_depth * points.h,
            reach,
            pca_reach,
            0.0,
        ],
        g: [grids as u32 - 1, grids as u32 - 1, 0, 0],
        base: crate::splat::WATER,
        absorb: absorb.extend(0.0).to_array(),
    }
}

/// An upper bound on the iterations any pixel needs besides its tile's spheres (every sample of
/// the march from entry to exit at `step`, the bisections, the gradient and the PCA sums, each
/// sum one iteration per row and per point): the same for every view of the caster.
fn iteration_bound(caster: &Caster<'_>, grids: &[CsrGrid], step: f32) -> u64 {
    let points = caster.points();
    let params = &caster.params;
    let (lo, hi) = (0..points.len()).fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), j| {
            let r = Vec3::splat(points.radius(j));
            (
                lo.min(points.positions[j] - r),
                hi.max(points.positions[j] + r),
            )
        },
    );
    let span = if points.is_empty() {
        0.0
    } else {
        (hi - lo).length()
    };
    let march = (f64::from(span) / f64::from(step)).ceil() as u64 + 4;
    let (pca_grid, density_grids) = grids.split_last().expect("the PCA grid is last");
    let per_sum = density_grids
        .iter()
        .map(|g| g.most_visited() + 9)
        .sum::<u64>()
        + 2;
    2 + (march + u64::from(params.bisection_steps) + 1) * per_sum + pca_grid.most_visited() + 11
}

impl crate::splat::GpuWaterPass for GpuCaster {
    fn size(&self) -> (u32, u32) {
        GpuCaster::size(self)
    }
    fn encode(
        &self,
        _queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
    ) -> Result<(), crate::Error> {
        Ok(GpuCaster::encode(self, encoder)?)
    }
    fn accumulation(&self) -> Result<(&wgpu::TextureView, &wgpu::TextureView), crate::Error> {
        Ok(GpuCaster::accumulation(self))
    }
    fn view(&self) -> Result<&View, crate::Error> {
        self.frame
            .as_ref()
            .map(|f| &f.view)
            .ok_or_else(crate::splat::water::unprepared)
    }
    fn created(&self) -> usize {
        GpuCaster::created(self)
    }
    fn after_submit(&mut self) {
        GpuCaster::after_submit(self);
    }
    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }
}
