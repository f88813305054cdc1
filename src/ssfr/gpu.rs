//! The screen-space passes on the GPU: `shaders/ssfr.wgsl`, compute passes one invocation per
//! pixel, each the CPU reference's per-pixel function ([`super::cpu`], the specification) over
//! the same inputs: the spheres and the projected thickness Gaussians in storage buffers,
//! binned into the same 16x16 tiles as the CPU's on the GPU ([`GpuTiles`], in the encoder
//! before the passes; the room for their lists from a recent binning of the same view, read
//! back without a wait, or counted on the CPU). The filters ping-pong between two depth
//! buffers; the shading after the read-back is the CPU's (`splat::shade`), as for the ray
//! caster. Tests compare every pass with the CPU's.

use super::cpu::{ScreenSpace, SsfrRender, SsfrTimings, depth_image, project_sources};
use super::{DepthFilter, FilterScales, SsfrError};
use crate::gpu::{GpuContext, GpuError};
use crate::splat::{Render, View};
use crate::view::gpu::GpuTiles;

/// The WGSL source of the passes.
pub const SHADER: &str = include_str!("../../shaders/ssfr.wgsl");

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
/// as spheres of three standard deviations).
struct Inputs {
    uniform: wgpu::Buffer,
    spheres: crate::gpu::Grow,
    sources: crate::gpu::Grow,
    source_spheres: crate::gpu::Grow,
    tiles: GpuTiles,
    source_tiles: GpuTiles,
}

impl Inputs {
    fn new(device: &wgpu::Device) -> Self {
        let storage = |label| crate::gpu::Grow::new(label, wgpu::BufferUsages::STORAGE);
        let tiles = GpuTiles::new(device);
        Self {
            uniform: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("ssfr params"),
                size: std::mem::size_of::<RawSsfrParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            spheres: storage("ssfr spheres"),
            sources: storage("ssfr sources"),
            source_spheres: storage("ssfr source spheres"),
            source_tiles: tiles.sharing(device),
            tiles,
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

    /// Uploads `screen`'s spheres and thickness Gaussians for view `v` through `queue` into
    /// buffers kept from view to view (grown when a view needs more; the bind groups made anew
    /// only then or when the filter or the size changes, [`Self::created`]) and makes the
    /// targets for its size when they differ. Their tiles are binned on the GPU by
    /// [`Self::encode`] ([`GpuTiles`]), in room planned here ([`GpuTiles::plan`]: refused as
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
        let i = &mut self.inputs;
        // the tiles' room, from a recent binning of the same view or counted here (refused as
        // the CPU's binning refuses), and the lists' length limit
        let (room, most) = i
            .tiles
            .plan(v, spheres.len(), |k| screen.sphere_of(k))
            .map_err(SsfrError::from)?;
        let (source_room, source_most) = i
            .source_tiles
            .plan(v, sources.len(), source_sphere)
            .map_err(SsfrError::from)?;
        if most.max(source_most) > MAX_TILE_ITEMS {
            return Err(SsfrError::TooDense {
                items: most.max(source_most),
                limit: MAX_TILE_ITEMS,
            }
            .into());
        }
        let uniforms = raw_params(screen, v, v.tiles().0);
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let mut created = 0;
        if self
            .targets
            .as_ref()
            .map_or((0, 0), |t| (t.width, t.height))
            != (w, h)
        {
            self.targets = Some(Targets::new(device, w, h));
            created += 1;
        }
        queue.write_buffer(&i.uniform, 0, bytemuck::bytes_of(&uniforms));
        created += crate::gpu::write_grown(
            device,
            queue,
            [
                (&mut i.spheres, bytemuck::cast_slice(&spheres)),
                (&mut i.sources, bytemuck::cast_slice(&projected)),
                (&mut i.source_spheres, bytemuck::cast_slice(&source_spheres)),
            ],
        );
        let queued = (device, queue);
        i.tiles.prepare(
            queued,
            v,
            (i.spheres.buffer(), spheres.len() as u32, 1),
            room,
        )?;
        i.source_tiles.prepare(
            queued,
            v,
            (i.source_spheres.buffer(), sources.len() as u32, 1),
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
