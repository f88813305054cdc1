//! The screen-space passes on the GPU: `shaders/ssfr.wgsl`, compute passes one invocation per
//! pixel, each the CPU reference's per-pixel function ([`super::cpu`], the specification) over
//! the same inputs: the spheres and the projected thickness Gaussians in storage buffers, made
//! on the GPU from the points with the narrow band (`GpuBand`, `shaders/ssfr_band.wgsl`; the
//! CPU's uploaded without it), binned into the same 16x16 tiles as the CPU's on the GPU
//! ([`GpuTiles`], in the encoder before the passes; the room for their lists from a recent
//! binning of a like view, read back without a wait, or counted on the CPU). The filters
//! ping-pong between two depth buffers; the shading after the read-back is the CPU's
//! (`splat::shade`), as for the ray caster. Tests compare every pass with the CPU's.

use super::cpu::{ScreenSpace, SsfrRender, SsfrTimings, depth_image, project_sources};
use super::{DepthFilter, FilterScales, SsfrError};
use crate::gpu::{GpuContext, GpuError};
use crate::splat::{Render, View};
use crate::view::gpu::GpuTiles;

/// The WGSL source of the passes.
pub const SHADER: &str = include_str!("../../shaders/ssfr.wgsl");

/// The WGSL source of the narrow band's passes and of the inputs made from it (`GpuBand`).
pub const BAND_SHADER: &str = concat!(
    include_str!("../../shaders/lnm.wgsl"),
    include_str!("../../shaders/ssfr_band.wgsl")
);

/// The band passes' own uniforms (`SsfrBand` in the WGSL, 176 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawSsfrBand {
    /// sphere radius and thickness sigma in kernel radii, the reference radius, the voxel edge
    pub a: [f32; 4],
    /// voxels of the domain, -, -, -
    pub b: [u32; 4],
    /// the view: world to view, view to clip
    pub view: [[f32; 4]; 4],
    pub proj: [[f32; 4]; 4],
    /// width, height, the pixel's world size at depth 1 (orthographic: the pixel's),
    /// orthographic (1) or perspective (0)
    pub screen: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<RawSsfrBand>() == 176);

/// The uniforms of the passes (`Params` in the WGSL, 160 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawSsfrParams {
    pub inv_view: [[f32; 4]; 4],
    /// width, height, tan_half.x, tan_half.y
    pub screen: [f32; 4],
    /// orthographic (0/1), tiles along x, filter half width, -
    pub a: [u32; 4],
    /// sigma_px, sigma_depth, range, clamp (world units)
    pub b: [f32; 4],
    /// curvature step, pixel size at depth 1, thickness sigma (world), -
    pub c: [f32; 4],
    /// the water's colour before the tint (rgb)
    pub base: [f32; 4],
    /// absorption per world length (rgb)
    pub absorb: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<RawSsfrParams>() == 160);

/// No fluid (`NONE` in the WGSL; the CPU's infinity).
const NONE: f32 = 1e30;

/// Most items a tile's list may hold: llvmpipe ends an invocation's loops after 65,535
/// iterations in total, so a longer list would be cut silently there.
pub const MAX_TILE_ITEMS: usize = 60_000;

/// The passes (compiled once) and, once prepared, one view's inputs and targets: the
/// screen-space water for the caller's encoder, like [`crate::raycast::gpu::GpuCaster`]. The
/// results are `(tint, 1)` and `(normal, depth)` in `Rgba32Float` textures
/// ([`GpuSsfr::accumulation`]), what the splats' shading and the GPU optics read.
pub struct GpuSsfr {
    depth: wgpu::ComputePipeline,
    filters: [wgpu::ComputePipeline; 4],
    thickness: wgpu::ComputePipeline,
    thickness_filter: wgpu::ComputePipeline,
    shade: wgpu::ComputePipeline,
    targets: Option<Targets>,
    inputs: Inputs,
    created: usize,
    frame: Option<Frame>,
}

/// A view's inputs, in buffers kept from view to view (grown when a view needs more): the
/// spheres and the projected thickness Gaussians, binned into tiles on the GPU (the Gaussians
/// as spheres of three standard deviations); made on the CPU and uploaded, or made on the GPU
/// from the points by the band's passes (`GpuBand`).
struct Inputs {
    uniform: wgpu::Buffer,
    spheres: crate::gpu::Grow,
    sources: crate::gpu::Grow,
    source_spheres: crate::gpu::Grow,
    tiles: GpuTiles,
    source_tiles: GpuTiles,
    band: GpuBand,
    /// Whether the last [`GpuSsfr::prepare`] made the inputs on the GPU.
    band_on_gpu: bool,
}

/// The passes' entry points, in the order [`GpuBand`] keeps their pipelines.
const BAND_ENTRIES: [&str; 7] = [
    "cs_count",
    "cs_first",
    "cs_second",
    "cs_radii",
    "cs_spheres",
    "cs_sources",
    "cs_project",
];

/// The narrow band of the points and the screen-space inputs made from it on the GPU (issue 37:
/// `ScreenSpace` made them on the CPU for every frame), `shaders/ssfr_band.wgsl` over the
/// points uploaded with their radii: the band on the dense voxels of its domain (the passes of
/// `lnm.wgsl`, as `lnm::gpu::ResidentBand` runs them but with each voxel's offsets' sum and each
/// point's voxel), then a depth sphere per point (radius 0 outside the band) and a thickness
/// Gaussian per voxel (radius 0 where it is empty), so that each list's length is known on the
/// host (the points, the voxels) and each tile's items are the CPU's, in the CPU's order; the
/// Gaussians projected into the view. Equal to the CPU's inputs to the fixed-point sums (the
/// centroids within 2^-16 voxel edges, the radii within 2^-12 of the reference radius, the
/// volumes within 2^-24 of a point of radius h), tested in `tests/gpu.rs`.
struct GpuBand {
    pipelines: [wgpu::ComputePipeline; BAND_ENTRIES.len()],
    lnm_uniform: wgpu::Buffer,
    uniform: wgpu::Buffer,
    points: crate::gpu::Grow,
    counts: crate::gpu::Grow,
    sums: crate::gpu::Grow,
    voxel_of: crate::gpu::Grow,
    labels: crate::gpu::Grow,
    radius_sums: crate::gpu::Grow,
    props: crate::gpu::Grow,
    /// The passes' bind groups, with the output buffers they hold (grown by the inputs made on
    /// the CPU too).
    binds: Option<([wgpu::BindGroup; BAND_ENTRIES.len()], [wgpu::Buffer; 3])>,
    /// Points and voxels of the last [`GpuBand::prepare`].
    count: u32,
    voxels: u32,
}

impl GpuBand {
    fn new(device: &wgpu::Device) -> Self {
        let uniform = |label, size| crate::gpu::uniform_buffer(device, label, size);
        // (read back by the tests)
        let storage = |label| {
            crate::gpu::Grow::new(
                label,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            )
        };
        Self {
            pipelines: crate::gpu::compute_pipelines(
                device,
                "ssfr band",
                BAND_SHADER,
                BAND_ENTRIES,
            ),
            lnm_uniform: uniform(
                "ssfr band lnm params",
                std::mem::size_of::<crate::lnm::gpu::RawLnmParams>() as u64,
            ),
            uniform: uniform(
                "ssfr band params",
                std::mem::size_of::<RawSsfrBand>() as u64,
            ),
            points: storage("ssfr band points"),
            counts: storage("ssfr band counts"),
            sums: storage("ssfr band sums"),
            voxel_of: storage("ssfr band voxel of"),
            labels: storage("ssfr band labels"),
            radius_sums: storage("ssfr band radius sums"),
            props: storage("ssfr band source props"),
            binds: None,
            count: 0,
            voxels: 0,
        }
    }

    /// Uploads the points of `screen`, writes the passes' uniforms for view `v` and the band's
    /// `domain`, and makes the buffers (the outputs: `spheres`, a `vec4` per point;
    /// `source_spheres` and `projected`, one per voxel) and bind groups the passes need; how
    /// many it made.
    fn prepare(
        &mut self,
        (device, queue): (&wgpu::Device, &wgpu::Queue),
        screen: &ScreenSpace<'_>,
        v: &View,
        (lo, edge, dims): crate::lnm::gpu::BandDomain,
        [spheres, source_spheres, projected]: [&mut crate::gpu::Grow; 3],
    ) -> usize {
        let (positions, radii) = screen.points();
        let n = positions.len() as u64;
        let voxels = dims.iter().map(|&d| u64::from(d)).product::<u64>();
        let points: Vec<[f32; 4]> = positions
            .iter()
            .zip(radii)
            .map(|(p, &r)| p.extend(r).to_array())
            .collect();
        let made = [
            self.points
                .write(device, queue, bytemuck::cast_slice(&points)),
            self.counts.reserve(device, voxels * 4),
            self.sums.reserve(device, voxels * 12),
            self.voxel_of.reserve(device, n * 4),
            self.labels.reserve(device, voxels * 4),
            self.radius_sums.reserve(device, voxels * 8),
            self.props.reserve(device, voxels * 8),
            spheres.reserve(device, n * 16),
            source_spheres.reserve(device, voxels * 16),
            projected.reserve(device, voxels * 16),
        ];
        let mut created = made.iter().filter(|&&m| m).count();
        let outputs = [&*spheres, &*source_spheres, &*projected].map(|g| g.buffer().clone());
        if created > 0 || self.binds.as_ref().is_none_or(|(_, held)| *held != outputs) {
            self.binds = Some((
                self.bind_groups(device, [spheres, source_spheres, projected]),
                outputs,
            ));
            created += BAND_ENTRIES.len();
        }
        self.count = n as u32;
        self.voxels = voxels as u32;
        let lnm = crate::lnm::gpu::RawLnmParams {
            lo: lo.extend(1.0 / edge).to_array(),
            dims: [dims[0], dims[1], dims[2], n as u32],
            misc: [screen.params().lnm.n_min, crate::lnm::gpu::SCALE, 1, 0],
        };
        queue.write_buffer(&self.lnm_uniform, 0, bytemuck::bytes_of(&lnm));
        let params = screen.params();
        let (view, _, proj) = v.matrices();
        let image = depth_image(v, Vec::new());
        let band = RawSsfrBand {
            a: [
                params.sphere_radius,
                params.thickness_sigma,
                screen.reference_radius(),
                edge,
            ],
            b: [voxels as u32, 0, 0, 0],
            view: view.to_cols_array_2d(),
            proj: proj.to_cols_array_2d(),
            screen: [
                v.width as f32,
                v.height as f32,
                image.pixel_size,
                if v.is_orthographic() { 1.0 } else { 0.0 },
            ],
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&band));
        created
    }

    /// The passes' bind groups over the kept buffers and the outputs.
    fn bind_groups(
        &self,
        device: &wgpu::Device,
        [spheres, source_spheres, projected]: [&crate::gpu::Grow; 3],
    ) -> [wgpu::BindGroup; BAND_ENTRIES.len()] {
        let (lnm, band) = (&self.lnm_uniform, &self.uniform);
        let (points, counts, sums, voxel_of, labels, radius_sums, props) = (
            self.points.buffer(),
            self.counts.buffer(),
            self.sums.buffer(),
            self.voxel_of.buffer(),
            self.labels.buffer(),
            self.radius_sums.buffer(),
            self.props.buffer(),
        );
        let (spheres, source_spheres, projected) = (
            spheres.buffer(),
            source_spheres.buffer(),
            projected.buffer(),
        );
        let entries: [&[(u32, &wgpu::Buffer)]; BAND_ENTRIES.len()] = [
            &[(0, lnm), (1, points), (2, counts), (3, sums), (4, voxel_of)],
            &[(0, lnm), (2, counts), (5, labels)],
            &[(0, lnm), (2, counts), (5, labels)],
            &[
                (0, lnm),
                (1, points),
                (4, voxel_of),
                (6, band),
                (7, radius_sums),
            ],
            &[
                (0, lnm),
                (1, points),
                (4, voxel_of),
                (5, labels),
                (6, band),
                (8, spheres),
            ],
            &[
                (0, lnm),
                (2, counts),
                (3, sums),
                (6, band),
                (7, radius_sums),
                (9, source_spheres),
                (10, props),
            ],
            &[(6, band), (9, source_spheres), (10, props), (11, projected)],
        ];
        std::array::from_fn(|k| {
            crate::gpu::buffer_bind_group(device, &self.pipelines[k], entries[k])
        })
    }

    /// Records the passes [`Self::prepare`] made ready into `encoder`.
    fn encode(&self, encoder: &mut wgpu::CommandEncoder) {
        let Some((binds, _)) = self.binds.as_ref() else {
            return;
        };
        let (n, voxels) = (u64::from(self.count), u64::from(self.voxels));
        encoder.clear_buffer(self.counts.buffer(), 0, Some(voxels * 4));
        encoder.clear_buffer(self.sums.buffer(), 0, Some(voxels * 12));
        encoder.clear_buffer(self.radius_sums.buffer(), 0, Some(voxels * 8));
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("ssfr band"),
            timestamp_writes: None,
        });
        // per point: the counts; per voxel: the labels; per point: the radii and spheres; per
        // voxel: the sources and their projection
        for (k, items) in [n, voxels, voxels, n, n, voxels, voxels]
            .into_iter()
            .enumerate()
        {
            let (gx, gy) = crate::lnm::gpu::groups(items);
            if gx * gy == 0 {
                continue;
            }
            pass.set_pipeline(&self.pipelines[k]);
            pass.set_bind_group(0, &binds[k], &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
    }
}

impl Inputs {
    fn new(device: &wgpu::Device) -> Self {
        let storage = |label| crate::gpu::Grow::new(label, wgpu::BufferUsages::STORAGE);
        let tiles = GpuTiles::new(device);
        Self {
            uniform: crate::gpu::uniform_buffer(
                device,
                "ssfr params",
                std::mem::size_of::<RawSsfrParams>() as u64,
            ),
            spheres: storage("ssfr spheres"),
            sources: storage("ssfr sources"),
            source_spheres: storage("ssfr source spheres"),
            source_tiles: tiles.sharing(device),
            tiles,
            band: GpuBand::new(device),
            band_on_gpu: false,
        }
    }
}

/// The per-size buffers and textures.
struct Targets {
    width: u32,
    height: u32,
    /// The filters' ping-pong pair; the spheres' depth lands in the first.
    depth: [wgpu::Buffer; 2],
    raw: wgpu::Buffer,
    thick_raw: wgpu::Buffer,
    thick: wgpu::Buffer,
    colour: wgpu::Texture,
    normal_depth: wgpu::Texture,
    views: (wgpu::TextureView, wgpu::TextureView),
}

/// One prepared view: its bind groups (holding its inputs) and what the encoder records.
struct Frame {
    view: View,
    depth: wgpu::BindGroup,
    /// The filter's pipeline index and its two bind groups (a -> b, b -> a).
    filter: Option<(usize, [wgpu::BindGroup; 2])>,
    iterations: usize,
    /// Which depth buffer holds the filtered depth.
    last: usize,
    thickness: wgpu::BindGroup,
    thickness_filter: wgpu::BindGroup,
    shade: wgpu::BindGroup,
}

impl Targets {
    fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let pixels = u64::from(width) * u64::from(height);
        let storage = wgpu::BufferUsages::STORAGE;
        let work = |label| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (4 * pixels).max(16),
                usage: storage | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
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
        let (colour, normal_depth) = (texture("ssfr colour"), texture("ssfr normal and depth"));
        let views = (
            colour.create_view(&Default::default()),
            normal_depth.create_view(&Default::default()),
        );
        Self {
            width,
            height,
            depth: [work("ssfr depth a"), work("ssfr depth b")],
            raw: work("ssfr raw depth"),
            thick_raw: work("ssfr raw thickness"),
            thick: work("ssfr thickness"),
            colour,
            normal_depth,
            views,
        }
    }
}

/// The passes' uniforms for view `v` of `screen`, whose spheres were binned into `tw` tiles a row.
fn raw_params(screen: &ScreenSpace<'_>, v: &View, tw: usize) -> RawSsfrParams {
    let params = screen.params();
    let (w, h) = (v.width, v.height);
    let scales = FilterScales::of(params, screen.sphere());
    let image = depth_image(v, Vec::new());
    let absorb = glam::Vec3::from(params.absorption) / screen.reference_radius();
    RawSsfrParams {
        inv_view: v.inv_view.to_cols_array_2d(),
        screen: [w as f32, h as f32, v.tan_half.x, v.tan_half.y],
        a: [
            u32::from(v.is_orthographic()),
            tw as u32,
            scales.radius_px,
            0,
        ],
        b: [
            scales.sigma_px,
            scales.sigma_depth,
            scales.range,
            scales.clamp,
        ],
        c: [
            scales.step,
            image.pixel_size,
            params.thickness_sigma_range * screen.reference_radius(),
            0.0,
        ],
        base: crate::splat::WATER,
        absorb: absorb.extend(0.0).to_array(),
    }
}

impl GpuSsfr {
    /// Compiles the passes.
    pub fn new(device: &wgpu::Device) -> Result<Self, GpuError> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let [
            depth,
            narrow,
            bilateral,
            plane,
            flow,
            thickness,
            thickness_filter,
            shade,
        ] = crate::gpu::compute_pipelines(
            device,
            "ssfr",
            SHADER,
            [
                "cs_depth",
                "cs_narrow_range",
                "cs_bilateral",
                "cs_plane",
                "cs_curvature_flow",
                "cs_thickness",
                "cs_thickness_filter",
                "cs_shade",
            ],
        );
        let passes = Self {
            depth,
            filters: [narrow, bilateral, plane, flow],
            thickness,
            thickness_filter,
            shade,
            targets: None,
            inputs: Inputs::new(device),
            created: 0,
            frame: None,
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()));
        }
        Ok(passes)
    }

    /// The size of the targets (0 x 0 before the first [`GpuSsfr::prepare`]).
    #[must_use]
    pub fn size(&self) -> (u32, u32) {
        self.targets
            .as_ref()
            .map_or((0, 0), |t| (t.width, t.height))
    }

    /// The results' textures, `(tint, 1)` and `(normal, depth)` per pixel (zero where no fluid),
    /// after [`GpuSsfr::prepare`].
    pub fn accumulation(&self) -> Result<(&wgpu::TextureView, &wgpu::TextureView), GpuError> {
        let t = self.targets.as_ref().ok_or_else(unprepared)?;
        Ok((&t.views.0, &t.views.1))
    }

    /// Makes `screen`'s spheres and thickness Gaussians for view `v` in buffers kept from view
    /// to view (grown when a view needs more; the bind groups made anew only then or when the
    /// filter or the size changes, [`Self::created`]) and makes the targets for its size when
    /// they differ. With the narrow band (the default) they are made on the GPU from the points
    /// (`GpuBand`: the CPU uploads the points and plans); without it, or where the band's
    /// dense domain would not fit the GPU's buffers or be mostly empty (far spray), on the CPU
    /// ([`ScreenSpace`]'s) and uploaded. Their tiles are binned on the GPU by [`Self::encode`] ([`GpuTiles`]), in room
    /// planned here ([`GpuTiles::plan`]: from a recent binning of the same view, else counted
    /// on the CPU, for the band's inputs over every point and every voxel, a bound; refused as
    /// the CPU's binning refuses, and when a tile would hold more than [`MAX_TILE_ITEMS`]).
    pub fn prepare(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        screen: &ScreenSpace<'_>,
        v: &View,
    ) -> Result<(), crate::Error> {
        let params = screen.params();
        let (w, h) = (v.width, v.height);
        let i = &mut self.inputs;
        let mut created = 0;
        // the two paths bin other lists (a sphere per point and a Gaussian per voxel, or the
        // band's spheres and a Gaussian per full voxel or per point): a binning's statistics
        // size only the lists of its own path (the CPU's lists sized from the GPU's
        // statistics lost most of their Gaussians' pairs: found by tests/ssfr.rs)
        let last_on_gpu = i.band_on_gpu;
        let domain = band_domain(device, screen);
        if domain.is_some() && !last_on_gpu {
            i.tiles.forget();
            i.source_tiles.forget();
        }
        let planned =
            domain.and_then(|(d, largest)| band_plan(i, screen, v, (d, largest)).map(|p| (d, p)));
        let ((room, most), (source_room, source_most), counts) =
            if let Some((domain, plans)) = planned {
                created += i.band.prepare(
                    (device, queue),
                    screen,
                    v,
                    domain,
                    [&mut i.spheres, &mut i.source_spheres, &mut i.sources],
                );
                i.band_on_gpu = true;
                let voxels = domain.2.iter().product::<u32>();
                (plans.0, plans.1, (screen.points().0.len(), voxels as usize))
            } else {
                if last_on_gpu {
                    i.tiles.forget();
                    i.source_tiles.forget();
                }
                i.band_on_gpu = false;
                let spheres: Vec<[f32; 4]> = (0..screen.drawn())
                    .map(|k| {
                        let (c, r) = screen.sphere_of(k);
                        [c.x, c.y, c.z, r]
                    })
                    .collect();
                let sources = screen.sources();
                let projected: Vec<[f32; 4]> = project_sources(v, sources)
                    .into_iter()
                    .map(|p| p.map_or([0.0; 4], |(c, k2, a)| [c.x, c.y, k2, a]))
                    .collect();
                let source_sphere = |k: usize| (sources[k].centre, 3.0 * sources[k].sigma);
                let source_spheres: Vec<[f32; 4]> = (0..sources.len())
                    .map(|k| {
                        let (c, r) = source_sphere(k);
                        [c.x, c.y, c.z, r]
                    })
                    .collect();
                // the tiles' room, from a recent binning of the same view or counted here
                // (refused as the CPU's binning refuses), and the lists' length limit
                let plans = (
                    i.tiles
                        .plan(v, spheres.len(), |k| screen.sphere_of(k))
                        .map_err(SsfrError::from)?,
                    i.source_tiles
                        .plan(v, sources.len(), source_sphere)
                        .map_err(SsfrError::from)?,
                );
                created += crate::gpu::write_grown(
                    device,
                    queue,
                    [
                        (&mut i.spheres, bytemuck::cast_slice(&spheres)),
                        (&mut i.sources, bytemuck::cast_slice(&projected)),
                        (&mut i.source_spheres, bytemuck::cast_slice(&source_spheres)),
                    ],
                );
                (plans.0, plans.1, (spheres.len(), sources.len()))
            };
        if most.max(source_most) > MAX_TILE_ITEMS {
            return Err(SsfrError::TooDense {
                items: most.max(source_most),
                limit: MAX_TILE_ITEMS,
            }
            .into());
        }
        let uniforms = raw_params(screen, v, v.tiles().0);
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        if self
            .targets
            .as_ref()
            .map_or((0, 0), |t| (t.width, t.height))
            != (w, h)
        {
            self.targets = Some(Targets::new(device, w, h));
            created += 1;
        }
        let i = &mut self.inputs;
        queue.write_buffer(&i.uniform, 0, bytemuck::bytes_of(&uniforms));
        let queued = (device, queue);
        i.tiles
            .prepare(queued, v, (i.spheres.buffer(), counts.0 as u32, 1), room)?;
        i.source_tiles.prepare(
            queued,
            v,
            (i.source_spheres.buffer(), counts.1 as u32, 1),
            source_room,
        )?;
        created += i.tiles.created() + i.source_tiles.created();
        let iterations = params.filter_iterations() as usize;
        let index = match params.filter {
            DepthFilter::NarrowRange => Some(0),
            DepthFilter::Bilateral => Some(1),
            DepthFilter::Plane => Some(2),
            DepthFilter::CurvatureFlow => Some(3),
            DepthFilter::None => None,
        }
        .filter(|_| iterations > 0);
        // the bind groups hold the buffers and targets: kept while none of them is new and the
        // filter is the same
        if let Some(f) = &mut self.frame
            && created == 0
            && f.filter.as_ref().map(|(k, _)| *k) == index
            && f.iterations == iterations
        {
            f.view = *v;
            self.created = 0;
            if let Some(e) = pollster::block_on(scope.pop()) {
                return Err(GpuError::Validation(e.to_string()).into());
            }
            return Ok(());
        }
        let frame = self.frame_of(device, v, index, iterations)?;
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        self.frame = Some(frame);
        self.created = created + 1;
        Ok(())
    }

    /// The bind groups of view `v` over the kept inputs and targets, with the depth filter
    /// `index` (into the filters) run `iterations` times.
    fn frame_of(
        &self,
        device: &wgpu::Device,
        v: &View,
        index: Option<usize>,
        iterations: usize,
    ) -> Result<Frame, GpuError> {
        let t = self.targets.as_ref().ok_or_else(unprepared)?;
        let i = &self.inputs;
        let uniform = &i.uniform;
        let (sphere_buf, tile_starts, tile_items) =
            (i.spheres.buffer(), i.tiles.starts(), i.tiles.items());
        let (source_buf, source_starts, source_items) = (
            i.sources.buffer(),
            i.source_tiles.starts(),
            i.source_tiles.items(),
        );
        let group = |p: &wgpu::ComputePipeline, entries: &[(u32, wgpu::BindingResource<'_>)]| {
            crate::gpu::bind_group(device, p, entries)
        };
        fn b(buffer: &wgpu::Buffer) -> wgpu::BindingResource<'_> {
            buffer.as_entire_binding()
        }
        let depth = group(
            &self.depth,
            &[
                (0, b(uniform)),
                (1, b(sphere_buf)),
                (2, b(tile_starts)),
                (3, b(tile_items)),
                (6, b(&t.depth[0])),
            ],
        );
        let filter = index.map(|k| {
            let f = &self.filters[k];
            (
                k,
                [
                    group(
                        f,
                        &[(0, b(uniform)), (5, b(&t.depth[0])), (6, b(&t.depth[1]))],
                    ),
                    group(
                        f,
                        &[(0, b(uniform)), (5, b(&t.depth[1])), (6, b(&t.depth[0]))],
                    ),
                ],
            )
        });
        // after the iterations the filtered depth is in depth[iterations % 2]
        let last = if filter.is_some() { iterations % 2 } else { 0 };
        let thickness = group(
            &self.thickness,
            &[
                (0, b(uniform)),
                (2, b(source_starts)),
                (3, b(source_items)),
                (4, b(source_buf)),
                (6, b(&t.thick_raw)),
            ],
        );
        let thickness_filter = group(
            &self.thickness_filter,
            &[
                (0, b(uniform)),
                (5, b(&t.depth[last])),
                (6, b(&t.thick)),
                (7, b(&t.thick_raw)),
            ],
        );
        let shade = group(
            &self.shade,
            &[
                (0, b(uniform)),
                (5, b(&t.depth[last])),
                (7, b(&t.thick)),
                (8, wgpu::BindingResource::TextureView(&t.views.0)),
                (9, wgpu::BindingResource::TextureView(&t.views.1)),
            ],
        );
        Ok(Frame {
            view: *v,
            depth,
            filter,
            iterations,
            last,
            thickness,
            thickness_filter,
            shade,
        })
    }

    /// Whether the last [`Self::prepare`] made the view's inputs on the GPU (`GpuBand`: the
    /// narrow band's, where its domain fits), not on the CPU.
    #[must_use]
    pub fn band_on_gpu(&self) -> bool {
        self.inputs.band_on_gpu
    }

    /// Buffers, targets and bind groups the last [`Self::prepare`] made (0 in the steady state
    /// of a sequence).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// Starts the late read of the tiles' statistics ([`GpuTiles::plan`]) once the encoder
    /// [`Self::encode`] recorded into is submitted.
    pub fn after_submit(&mut self) {
        self.inputs.tiles.after_submit();
        self.inputs.source_tiles.after_submit();
    }

    /// Records the prepared view's passes into `encoder`.
    pub fn encode(&self, encoder: &mut wgpu::CommandEncoder) -> Result<(), GpuError> {
        let (t, f) = match (&self.targets, &self.frame) {
            (Some(t), Some(f)) => (t, f),
            _ => return Err(unprepared()),
        };
        let groups = (t.width.div_ceil(8), t.height.div_ceil(8));
        if self.inputs.band_on_gpu {
            self.inputs.band.encode(encoder);
        }
        self.inputs.tiles.encode(encoder);
        self.inputs.source_tiles.encode(encoder);
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.depth);
            pass.set_bind_group(0, &f.depth, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
        }
        encoder.copy_buffer_to_buffer(&t.depth[0], 0, &t.raw, 0, t.raw.size());
        let mut pass = encoder.begin_compute_pass(&Default::default());
        if let Some((k, g)) = &f.filter {
            pass.set_pipeline(&self.filters[*k]);
            for i in 0..f.iterations {
                pass.set_bind_group(0, &g[i % 2], &[]);
                pass.dispatch_workgroups(groups.0, groups.1, 1);
            }
        }
        for (pipeline, group) in [
            (&self.thickness, &f.thickness),
            (&self.thickness_filter, &f.thickness_filter),
            (&self.shade, &f.shade),
        ] {
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, group, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
        }
        Ok(())
    }

    /// Reads the prepared view's results back after its encoder ran: the same buffers as
    /// [`ScreenSpace::render_view`], shaded by the CPU's shading.
    pub fn read(&self, ctx: &GpuContext) -> Result<SsfrRender, GpuError> {
        let (t, f) = match (&self.targets, &self.frame) {
            (Some(t), Some(f)) => (t, f),
            _ => return Err(unprepared()),
        };
        let pixels = t.width as usize * t.height as usize;
        let depths = |b: &wgpu::Buffer| -> Result<Vec<f32>, GpuError> {
            let d: Vec<f32> = crate::gpu::read_buffer(ctx, b)?;
            Ok(d[..pixels]
                .iter()
                .map(|&z| if z >= NONE { f32::INFINITY } else { z })
                .collect())
        };
        let texels = |tex: &wgpu::Texture| -> Result<Vec<[f32; 4]>, GpuError> {
            let bytes = crate::gpu::read_texture(ctx, tex, 16)?;
            Ok(bytemuck::pod_collect_to_vec(&bytes))
        };
        let raw_depth = depths(&t.raw)?;
        let depth = depths(&t.depth[f.last])?;
        let thickness: Vec<f32> = crate::gpu::read_buffer(ctx, &t.thick)?;
        let colour = texels(&t.colour)?;
        let normal_depth = texels(&t.normal_depth)?;
        let image = crate::splat::cpu::shade_image(&colour, &normal_depth, &f.view);
        Ok(SsfrRender {
            render: Render {
                width: t.width,
                height: t.height,
                image,
                colour,
                normal_depth,
            },
            raw_depth,
            depth,
            thickness: thickness[..pixels].to_vec(),
            timings: SsfrTimings::default(),
        })
    }

    /// Every pass of `screen` from view `v`, run and read back (the timings are not split by
    /// pass: `depth_ms` holds the whole GPU run with its read-back).
    pub fn render(
        &mut self,
        ctx: &GpuContext,
        screen: &ScreenSpace<'_>,
        v: &View,
    ) -> Result<SsfrRender, crate::Error> {
        let started = std::time::Instant::now();
        self.prepare(&ctx.device, &ctx.queue, screen, v)?;
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.encode(&mut encoder)?;
        ctx.queue.submit([encoder.finish()]);
        self.after_submit();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        let mut out = self.read(ctx)?;
        out.timings.depth_ms = started.elapsed().as_secs_f64() * 1e3;
        Ok(out)
    }
}

/// The most voxels of the band's dense domain per point for [`GpuBand`], beyond
/// [`DENSE_ALWAYS`] voxels: a domain up to 64 times emptier than the bulk (about 8 points a
/// voxel), 544 bytes of the band's buffers a point at most.
const DENSE_PER_POINT: u64 = 8;

/// Voxels of the band's dense domain [`GpuBand`] takes whatever the points (4.5 MB of its
/// buffers).
const DENSE_ALWAYS: u64 = 1 << 16;

/// The band's dense domain where [`GpuBand`] may make the view's inputs of `screen` on the GPU:
/// with the narrow band, every radius at most the reference radius (its fixed-point sums'
/// range), the domain within the layout's and the GPU's limits and at most
/// [`DENSE_PER_POINT`] voxels a point (or [`DENSE_ALWAYS`]); with the largest radius. `None`
/// otherwise: the inputs are then made on the CPU, whose band says why a view cannot be drawn.
fn band_domain(
    device: &wgpu::Device,
    screen: &ScreenSpace<'_>,
) -> Option<(crate::lnm::gpu::BandDomain, f32)> {
    let params = screen.params();
    let (positions, radii) = screen.points();
    let h = screen.reference_radius();
    let largest = radii.iter().fold(0.0f32, |m, &r| m.max(r));
    if !params.narrow_band || largest > h {
        return None;
    }
    let domain = crate::lnm::gpu::ResidentBand::domain(positions, h, &params.lnm).ok()?;
    let voxels = domain.2.iter().map(|&d| u64::from(d)).product::<u64>();
    // the dense domain's buffers (68 bytes a voxel) kept near the points' own: a domain of far
    // spray, mostly empty voxels, keeps the CPU's sparse band
    let limit = crate::gpu::max_binding(device);
    let n = positions.len() as u64;
    if voxels * 16 > limit || n * 16 > limit || voxels > DENSE_PER_POINT * n + DENSE_ALWAYS {
        return None;
    }
    Some((domain, largest))
}

/// The tiles' room for [`GpuBand`]'s inputs of `screen` over `domain` (its points' largest
/// radius `largest`) in view `v`: planned over
/// every point and every voxel that holds a point (a voxel's Gaussian lies in the sphere around
/// the voxel's centre that reaches its corners and three sigma of the largest radius beyond).
/// `None` where the CPU's binning would refuse them (the CPU's inputs then say why).
fn band_plan(
    i: &mut Inputs,
    screen: &ScreenSpace<'_>,
    v: &View,
    ((lo, edge, dims), largest): (crate::lnm::gpu::BandDomain, f32),
) -> Option<((u32, usize), (u32, usize))> {
    let params = screen.params();
    let (positions, radii) = screen.points();
    let voxels = dims.iter().map(|&d| d as usize).product::<usize>();
    let spheres = i
        .tiles
        .plan(v, positions.len(), |k| {
            (positions[k], params.sphere_radius * radii[k])
        })
        .ok()?;
    let reach = 0.5 * 3f32.sqrt() * edge + 3.0 * params.thickness_sigma * largest;
    let (nx, ny) = (dims[0] as usize, dims[1] as usize);
    // which voxels hold a point, found only when the plan counts on the CPU (an empty voxel's
    // Gaussian has radius 0 there, and no tile holds it: `sphere_rect` of radius 0 is empty);
    // each point's voxel as `lnm.wgsl`'s `cs_count` and the CPU's band find it
    let full = std::sync::OnceLock::new();
    let full = || {
        full.get_or_init(|| {
            let inv = 1.0 / edge;
            let mut full = vec![false; voxels];
            for &p in positions {
                full[crate::lnm::dense_index(crate::lnm::voxel_at(p, lo, inv, dims), dims)] = true;
            }
            full
        })
    };
    let sources = i
        .source_tiles
        .plan(v, voxels, |k| {
            let coord = glam::Vec3::new(
                (k % nx) as f32,
                ((k / nx) % ny) as f32,
                (k / (nx * ny)) as f32,
            );
            (
                lo + (coord + 0.5) * edge,
                if full()[k] { reach } else { 0.0 },
            )
        })
        .ok()?;
    Some((spheres, sources))
}

fn unprepared() -> GpuError {
    GpuError::Validation("the screen-space passes have no prepared view".into())
}

/// Every screen-space pass of `screen` from view `v` on the GPU (compiles the passes; keep a
/// [`GpuSsfr`] to draw many).
pub fn render_view_gpu(
    ctx: &GpuContext,
    screen: &ScreenSpace<'_>,
    v: &View,
) -> Result<SsfrRender, crate::Error> {
    GpuSsfr::new(&ctx.device)?.render(ctx, screen, v)
}

impl crate::splat::GpuWaterPass for GpuSsfr {
    fn size(&self) -> (u32, u32) {
        GpuSsfr::size(self)
    }
    fn encode(
        &self,
        _queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
    ) -> Result<(), crate::Error> {
        Ok(GpuSsfr::encode(self, encoder)?)
    }
    fn accumulation(&self) -> Result<(&wgpu::TextureView, &wgpu::TextureView), crate::Error> {
        Ok(GpuSsfr::accumulation(self)?)
    }
    fn view(&self) -> Result<&View, crate::Error> {
        self.frame
            .as_ref()
            .map(|f| &f.view)
            .ok_or_else(crate::splat::water::unprepared)
    }
    fn created(&self) -> usize {
        GpuSsfr::created(self)
    }
    fn after_submit(&mut self) {
        GpuSsfr::after_submit(self);
    }
    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }
}
