//! EWA surfel splatting on the GPU: the three passes of [`crate::splat`] (whose CPU functions are
//! the specification) in `shaders/surfel_splat.wgsl`.
//!
//! Two ways to call it:
//! - headless: [`render_gpu`] renders into its own textures and reads the image and the
//!   accumulation buffers back;
//! - inside a game: [`SplatRenderer::new`] on the game's `wgpu::Device` with the format of the
//!   game's target, [`SplatRenderer::upload`] the surfels, then [`SplatRenderer::encode`] the three
//!   passes into the game's command encoder, drawing into the game's texture view. The crate
//!   creates no device and submits nothing there.

use std::time::Instant;

use serde::Serialize;
use wgpu::util::DeviceExt;

use crate::gpu::{self, GpuContext, GpuError, REQUIRED_FEATURES, entry, texture_2d};
use crate::splat::{Camera, Light, Render, SplatError, SplatMode, SplatParams, Surfel, View};

/// The WGSL source of the three passes.
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/surfel_splat.wgsl")
);

const ACCUMULATION: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
const DEPTH: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Surfels uploaded to the GPU (only the drawable ones; see [`Surfel::is_drawable`]), in chunks
/// no larger than the device's buffer limit. A clone shares the same GPU buffers.
#[derive(Clone, Debug)]
pub struct SurfelBuffer {
    chunks: Vec<(wgpu::Buffer, u32)>,
    /// Drawn by an indirect draw from this buffer's arguments (surfels made on the GPU,
    /// [`crate::surfels::gpu::ResidentSurfels`]): the one chunk's count is not known here.
    indirect: Option<wgpu::Buffer>,
    /// Surfels uploaded.
    pub len: usize,
    /// Surfels skipped as undrawable.
    pub skipped: usize,
    /// Surfels the single buffer holds (0 when chunked or empty); see [`SurfelBuffer::write`].
    capacity: usize,
}

impl SurfelBuffer {
    /// Surfels that live on the GPU: `instances` (a `VERTEX` buffer of [`Surfel`]s) drawn with
    /// the arguments in `args` (an `INDIRECT` buffer: 6 vertices, the instance count, 0, 0),
    /// both written by GPU passes; `capacity` the surfels `instances` holds.
    #[must_use]
    pub fn indirect(instances: wgpu::Buffer, args: wgpu::Buffer, capacity: usize) -> Self {
        Self {
            chunks: vec![(instances, 0)],
            indirect: Some(args),
            len: 0,
            skipped: 0,
            capacity,
        }
    }
    /// Replaces the surfels for the next submission, reusing the buffer while they fit and
    /// growing it geometrically (to the next power of two) when they do not, so that a sequence
    /// allocates only while its largest frame so far grows. Writes go through
    /// `queue.write_buffer`, so they take effect at the next submit. Whether it made a new
    /// buffer.
    pub fn write(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        surfels: &[Surfel],
    ) -> bool {
        let (kept, skipped) = crate::splat::drawable(surfels);
        let size = std::mem::size_of::<Surfel>() as u64;
        let max = device.limits().max_buffer_size / size;
        if kept.len() as u64 > max {
            // more than one buffer can hold: chunked, as `upload` makes them
            *self = SplatRenderer::upload(device, surfels);
            return true;
        }
        let grown = kept.len() > self.capacity || self.chunks.len() != 1 || self.indirect.is_some();
        if grown {
            let capacity = (kept.len().max(1).next_power_of_two() as u64).min(max) as usize;
            let buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("surfels"),
                size: capacity as u64 * size,
                usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            self.chunks = vec![(buffer, 0)];
            self.indirect = None;
            self.capacity = capacity;
        }
        if !kept.is_empty() {
            queue.write_buffer(&self.chunks[0].0, 0, bytemuck::cast_slice(&kept));
        }
        self.chunks[0].1 = kept.len() as u32;
        self.len = kept.len();
        self.skipped = skipped;
        grown
    }
}

/// Wall-clock milliseconds of each pass (each submitted and waited for on its own).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct PassTimes {
    pub visibility_ms: f64,
    pub attributes_ms: f64,
    pub shading_ms: f64,
}

impl PassTimes {
    /// Sum of the three passes.
    #[must_use]
    pub fn total_ms(&self) -> f64 {
        self.visibility_ms + self.attributes_ms + self.shading_ms
    }
}

struct Targets {
    width: u32,
    height: u32,
    depth: wgpu::TextureView,
    colour: wgpu::Texture,
    colour_view: wgpu::TextureView,
    normal: wgpu::Texture,
    normal_view: wgpu::TextureView,
}

/// The pipelines and intermediate targets of the three passes for one output format and size.
pub struct SplatRenderer {
    format: wgpu::TextureFormat,
    splat_layout: wgpu::BindGroupLayout,
    attributes_layout: wgpu::BindGroupLayout,
    shade_layout: wgpu::BindGroupLayout,
    visibility: wgpu::RenderPipeline,
    attributes: wgpu::RenderPipeline,
    shading: wgpu::RenderPipeline,
    targets: Targets,
    /// The uniforms and bind groups of [`SplatRenderer::encode_queued`] (one view per
    /// submission), made with the targets.
    uniforms: wgpu::Buffer,
    bound: BindGroups,
}

/// The bind groups of the three passes: uniforms; uniforms and pass 1's depth; uniforms and the
/// accumulation textures.
struct BindGroups {
    splat: wgpu::BindGroup,
    attributes: wgpu::BindGroup,
    shade: wgpu::BindGroup,
}

fn create_targets(device: &wgpu::Device, width: u32, height: u32) -> Targets {
    let texture = |label, format, usage| texture_2d(device, label, (width, height), format, usage);
    let accumulation = wgpu::TextureUsages::RENDER_ATTACHMENT
        | wgpu::TextureUsages::TEXTURE_BINDING
        | wgpu::TextureUsages::COPY_SRC;
    // pass 2 reads the depth too (the spheres' W2), beside its read-only attachment
    let depth = texture(
        "splat depth",
        DEPTH,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
    );
    let colour = texture("splat colour accumulation", ACCUMULATION, accumulation);
    let normal = texture("splat normal accumulation", ACCUMULATION, accumulation);
    Targets {
        width,
        height,
        depth: depth.create_view(&Default::default()),
        colour_view: colour.create_view(&Default::default()),
        normal_view: normal.create_view(&Default::default()),
        colour,
        normal,
    }
}

/// The bind group layouts of the three passes: the splats' uniforms (visibility), the uniforms
/// and the visibility depth (attributes), the uniforms and the accumulated targets (shading).
fn bind_group_layouts(device: &wgpu::Device) -> [wgpu::BindGroupLayout; 3] {
    let splat_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("splat uniforms"),
        entries: &[entry::uniform(0, wgpu::ShaderStages::VERTEX_FRAGMENT)],
    });
    let attributes_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("splat attributes"),
        entries: &[
            entry::uniform(0, wgpu::ShaderStages::VERTEX_FRAGMENT),
            wgpu::BindGroupLayoutEntry {
                binding: 3,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Depth,
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                count: None,
            },
        ],
    });
    let shade_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("splat shading"),
        entries: &[
            entry::uniform(0, wgpu::ShaderStages::VERTEX_FRAGMENT),
            entry::texture(1, wgpu::ShaderStages::FRAGMENT),
            entry::texture(2, wgpu::ShaderStages::FRAGMENT),
        ],
    });
    [splat_layout, attributes_layout, shade_layout]
}

impl SplatRenderer {
    /// Builds the pipelines for targets of `format` and the intermediate buffers for
    /// `width` x `height`. The device needs [`REQUIRED_FEATURES`].
    pub fn new(
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
        width: u32,
        height: u32,
    ) -> Result<Self, crate::Error> {
        check_device(device, width, height)?;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("surfel_splat"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let [splat_layout, attributes_layout, shade_layout] = bind_group_layouts(device);
        let splat_pipeline_layout =
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("splat"),
                bind_group_layouts: &[Some(&splat_layout)],
                ..Default::default()
            });
        let attributes_pipeline_layout =
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("splat attributes"),
                bind_group_layouts: &[Some(&attributes_layout)],
                ..Default::default()
            });
        let shade_pipeline_layout =
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("splat shading"),
                bind_group_layouts: &[Some(&shade_layout)],
                ..Default::default()
            });
        let surfel_layout = [Some(wgpu::VertexBufferLayout {
            array_stride: std::mem::size_of::<Surfel>() as u64,
            step_mode: wgpu::VertexStepMode::Instance,
            attributes: &wgpu::vertex_attr_array![0 => Float32x4, 1 => Float32x4, 2 => Float32x4, 3 => Float32x4],
        })];
        let additive = wgpu::BlendComponent {
            src_factor: wgpu::BlendFactor::One,
            dst_factor: wgpu::BlendFactor::One,
            operation: wgpu::BlendOperation::Add,
        };
        let accumulate = Some(wgpu::ColorTargetState {
            format: ACCUMULATION,
            blend: Some(wgpu::BlendState {
                color: additive,
                alpha: additive,
            }),
            write_mask: wgpu::ColorWrites::ALL,
        });
        let splat_pipeline =
            |label, fragment, targets: &[Option<wgpu::ColorTargetState>], write| {
                device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                    label: Some(label),
                    layout: Some(if write {
                        &splat_pipeline_layout
                    } else {
                        &attributes_pipeline_layout
                    }),
                    vertex: wgpu::VertexState {
                        module: &module,
                        entry_point: Some("vs_splat"),
                        compilation_options: Default::default(),
                        buffers: &surfel_layout,
                    },
                    primitive: wgpu::PrimitiveState::default(),
                    depth_stencil: Some(wgpu::DepthStencilState {
                        format: DEPTH,
                        depth_write_enabled: Some(write),
                        depth_compare: Some(wgpu::CompareFunction::LessEqual),
                        stencil: Default::default(),
                        bias: Default::default(),
                    }),
                    multisample: Default::default(),
                    fragment: Some(wgpu::FragmentState {
                        module: &module,
                        entry_point: Some(fragment),
                        compilation_options: Default::default(),
                        targets,
                    }),
                    multiview_mask: None,
                    cache: None,
                })
            };
        let visibility = splat_pipeline("splat visibility", "fs_visibility", &[], true);
        let attributes = splat_pipeline(
            "splat attributes",
            "fs_attributes",
            &[accumulate.clone(), accumulate],
            false,
        );
        let shading = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("splat shading"),
            layout: Some(&shade_pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_fullscreen"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_shade"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let targets = create_targets(device, width, height);
        let uniforms = crate::gpu::uniform_buffer(
            device,
            "splat uniforms (queued)",
            std::mem::size_of::<RawUniforms>() as u64,
        );
        let layouts = [&splat_layout, &attributes_layout, &shade_layout];
        let bound = bind_groups(device, layouts, &targets, &uniforms);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        Ok(Self {
            format,
            splat_layout,
            attributes_layout,
            shade_layout,
            visibility,
            attributes,
            shading,
            targets,
            uniforms,
            bound,
        })
    }

    /// The output format the shading pass writes.
    #[must_use]
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }

    /// Image size the intermediate buffers have.
    #[must_use]
    pub fn size(&self) -> (u32, u32) {
        (self.targets.width, self.targets.height)
    }

    /// Re-creates the intermediate buffers for a new image size.
    pub fn resize(
        &mut self,
        device: &wgpu::Device,
        width: u32,
        height: u32,
    ) -> Result<(), crate::Error> {
        check_size(device, width, height)?;
        if (width, height) != self.size() {
            self.targets = create_targets(device, width, height);
            self.bound = bind_groups(device, self.layouts(), &self.targets, &self.uniforms);
        }
        Ok(())
    }

    /// The accumulation textures after [`Self::encode`]: `(sum w colour, sum w)` and
    /// `(sum w normal, sum w depth)`, `Rgba32Float` (what the optics stage reads).
    #[must_use]
    pub fn accumulation(&self) -> (&wgpu::TextureView, &wgpu::TextureView) {
        (&self.targets.colour_view, &self.targets.normal_view)
    }

    /// Uploads the drawable surfels (the others are counted in `skipped`).
    #[must_use]
    pub fn upload(device: &wgpu::Device, surfels: &[Surfel]) -> SurfelBuffer {
        let (kept, skipped) = crate::splat::drawable(surfels);
        let per_chunk = (device.limits().max_buffer_size / std::mem::size_of::<Surfel>() as u64)
            .clamp(1, u64::from(u32::MAX)) as usize;
        let chunks = kept
            .chunks(per_chunk)
            .map(|c| {
                let buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("surfels"),
                    contents: bytemuck::cast_slice(c),
                    usage: wgpu::BufferUsages::VERTEX,
                });
                (buffer, c.len() as u32)
            })
            .collect();
        SurfelBuffer {
            chunks,
            indirect: None,
            len: kept.len(),
            skipped,
            capacity: 0,
        }
    }

    fn layouts(&self) -> [&wgpu::BindGroupLayout; 3] {
        [
            &self.splat_layout,
            &self.attributes_layout,
            &self.shade_layout,
        ]
    }

    fn bind_groups(&self, device: &wgpu::Device, view: &View) -> BindGroups {
        let uniforms = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("splat uniforms"),
            contents: bytemuck::bytes_of(&view.to_raw()),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        bind_groups(device, self.layouts(), &self.targets, &uniforms)
    }

    fn check_view(&self, view: &View) -> Result<(), crate::Error> {
        if (view.width, view.height) != self.size() {
            return Err(SplatError::InvalidParameter {
                name: "view",
                reason: format!(
                    "a {}x{} view for a renderer of {}x{}; call resize first",
                    view.width, view.height, self.targets.width, self.targets.height
                ),
            }
            .into());
        }
        Ok(())
    }

    /// Records the three passes into `encoder`, the image going to `target` (a view of a texture
    /// of [`Self::format`] and [`Self::size`]). Submitting is the caller's business.
    pub fn encode(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        surfels: &SurfelBuffer,
        view: &View,
    ) -> Result<(), crate::Error> {
        self.check_view(view)?;
        let bound = self.bind_groups(device, view);
        self.encode_passes(encoder, target, surfels, &bound);
        Ok(())
    }

    /// The three passes with the given bind groups (over the uniforms of the view).
    fn encode_passes(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        surfels: &SurfelBuffer,
        bound: &BindGroups,
    ) {
        self.encode_visibility(encoder, surfels, &bound.splat);
        self.encode_attributes(encoder, surfels, &bound.attributes);
        self.encode_shading(encoder, target, &bound.shade);
    }

    /// Records the shading pass alone over accumulation textures made elsewhere (`colour` and
    /// `normal` as [`Self::accumulation`] holds them, `Rgba32Float` of this renderer's size:
    /// the ray caster's, [`crate::raycast::gpu::GpuCaster::accumulation`]) into `target`, with
    /// the renderer's own uniform buffer written through the queue.
    pub fn encode_shading_of(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        (colour, normal): (&wgpu::TextureView, &wgpu::TextureView),
        view: &View,
    ) -> Result<(), crate::Error> {
        self.check_view(view)?;
        queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&view.to_raw()));
        let entry = |binding, resource| wgpu::BindGroupEntry { binding, resource };
        let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("splat shading of given accumulations"),
            layout: &self.shade_layout,
            entries: &[
                entry(0, self.uniforms.as_entire_binding()),
                entry(1, wgpu::BindingResource::TextureView(colour)),
                entry(2, wgpu::BindingResource::TextureView(normal)),
            ],
        });
        self.encode_shading(encoder, target, &bind);
        Ok(())
    }

    /// [`Self::encode`] with the renderer's own uniform buffer, written through the queue: no
    /// buffer or bind group is created. The write takes effect at the next submit, so a renderer
    /// records one view per submission this way (use [`Self::encode`] for several).
    pub fn encode_queued(
        &self,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        surfels: &SurfelBuffer,
        view: &View,
    ) -> Result<(), crate::Error> {
        self.check_view(view)?;
        queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&view.to_raw()));
        self.encode_passes(encoder, target, surfels, &self.bound);
        Ok(())
    }

    /// [`Self::encode_queued`] without the shading pass: the visibility and attribute passes
    /// fill the accumulation targets ([`Self::accumulation`]) for a pass that reads them (the
    /// GPU optics).
    pub fn encode_accumulation_queued(
        &self,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        surfels: &SurfelBuffer,
        view: &View,
    ) -> Result<(), crate::Error> {
        self.check_view(view)?;
        queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&view.to_raw()));
        self.encode_visibility(encoder, surfels, &self.bound.splat);
        self.encode_attributes(encoder, surfels, &self.bound.attributes);
        Ok(())
    }

    fn draw_surfels(&self, pass: &mut wgpu::RenderPass<'_>, surfels: &SurfelBuffer) {
        for (buffer, count) in &surfels.chunks {
            pass.set_vertex_buffer(0, buffer.slice(..));
            match &surfels.indirect {
                Some(args) => pass.draw_indirect(args, 0),
                None => pass.draw(0..6, 0..*count),
            }
        }
    }

    /// The depth buffer as pass 1 attaches it (cleared and written) and pass 2 (read-only, so
    /// that its fragments can also read it as a texture).
    fn depth_attachment(&self, write: bool) -> wgpu::RenderPassDepthStencilAttachment<'_> {
        wgpu::RenderPassDepthStencilAttachment {
            view: &self.targets.depth,
            depth_ops: write.then_some(wgpu::Operations {
                load: wgpu::LoadOp::Clear(1.0),
                store: wgpu::StoreOp::Store,
            }),
            stencil_ops: None,
        }
    }

    fn encode_visibility(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        surfels: &SurfelBuffer,
        bind: &wgpu::BindGroup,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("splat visibility"),
            color_attachments: &[],
            depth_stencil_attachment: Some(self.depth_attachment(true)),
            ..Default::default()
        });
        pass.set_pipeline(&self.visibility);
        pass.set_bind_group(0, bind, &[]);
        self.draw_surfels(&mut pass, surfels);
    }

    fn encode_attributes(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        surfels: &SurfelBuffer,
        bind: &wgpu::BindGroup,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("splat attributes"),
            color_attachments: &[
                crate::gpu::cleared(&self.targets.colour_view),
                crate::gpu::cleared(&self.targets.normal_view),
            ],
            depth_stencil_attachment: Some(self.depth_attachment(false)),
            ..Default::default()
        });
        pass.set_pipeline(&self.attributes);
        pass.set_bind_group(0, bind, &[]);
        self.draw_surfels(&mut pass, surfels);
    }

    fn encode_shading(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        bind: &wgpu::BindGroup,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("splat shading"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            ..Default::default()
        });
        pass.set_pipeline(&self.shading);
        pass.set_bind_group(0, bind, &[]);
        pass.draw(0..3, 0..1);
    }
}

/// The passes' bind groups over `uniforms`, the depth and the targets' accumulation views.
fn bind_groups(
    device: &wgpu::Device,
    [splat_layout, attributes_layout, shade_layout]: [&wgpu::BindGroupLayout; 3],
    targets: &Targets,
    uniforms: &wgpu::Buffer,
) -> BindGroups {
    let splat = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("splat uniforms"),
        layout: splat_layout,
        entries: &[wgpu::BindGroupEntry {
            binding: 0,
            resource: uniforms.as_entire_binding(),
        }],
    });
    let attributes = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("splat attributes"),
        layout: attributes_layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: uniforms.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 3,
                resource: wgpu::BindingResource::TextureView(&targets.depth),
            },
        ],
    });
    let shade = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("splat shading"),
        layout: shade_layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: uniforms.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: wgpu::BindingResource::TextureView(&targets.colour_view),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: wgpu::BindingResource::TextureView(&targets.normal_view),
            },
        ],
    });
    BindGroups {
        splat,
        attributes,
        shade,
    }
}

/// Whether `device` can splat `width` x `height` images: the size within the device's texture
/// limit and [`MAX_SIZE`](crate::splat::MAX_SIZE), and the [`REQUIRED_FEATURES`].
pub fn check_device(device: &wgpu::Device, width: u32, height: u32) -> Result<(), crate::Error> {
    check_size(device, width, height)?;
    if !device.features().contains(REQUIRED_FEATURES) {
        return Err(GpuError::MissingFeature {
            adapter: "the given device".into(),
            feature: "FLOAT32_BLENDABLE (additive blending into 32-bit float targets)",
        }
        .into());
    }
    Ok(())
}

fn check_size(device: &wgpu::Device, width: u32, height: u32) -> Result<(), crate::Error> {
    let max = device
        .limits()
        .max_texture_dimension_2d
        .min(crate::splat::MAX_SIZE);
    if width == 0 || height == 0 || width > max || height > max {
        return Err(SplatError::InvalidSize { width, height, max }.into());
    }
    Ok(())
}

/// Renders headless: the image and the accumulation buffers read back.
pub fn render_gpu(
    ctx: &GpuContext,
    surfels: &[Surfel],
    camera: &Camera,
    light: &Light,
    params: &SplatParams,
    width: u32,
    height: u32,
) -> Result<Render, crate::Error> {
    let view = View::new(camera, light, params, width, height)?;
    render_view_gpu(ctx, surfels, &view)
}

/// [`render_gpu`] for a prepared view.
pub fn render_view_gpu(
    ctx: &GpuContext,
    surfels: &[Surfel],
    view: &View,
) -> Result<Render, crate::Error> {
    crate::splat::check_cost(surfels.len(), crate::splat::fragments(surfels, view), view)?;
    render_buffer_gpu(ctx, &SplatRenderer::upload(&ctx.device, surfels), view)
}

/// [`render_view_gpu`] of surfels already on the GPU (an indirect [`SurfelBuffer`] too).
pub fn render_buffer_gpu(
    ctx: &GpuContext,
    surfels: &SurfelBuffer,
    view: &View,
) -> Result<Render, crate::Error> {
    let renderer = SplatRenderer::new(
        &ctx.device,
        wgpu::TextureFormat::Rgba8Unorm,
        view.width,
        view.height,
    )?;
    Ok(render_timed(ctx, &renderer, surfels, view)?.0)
}

/// Renders headless with each pass submitted and waited for on its own (for benchmarks), and
/// reads the results back.
pub fn render_timed(
    ctx: &GpuContext,
    renderer: &SplatRenderer,
    surfels: &SurfelBuffer,
    view: &View,
) -> Result<(Render, PassTimes), crate::Error> {
    renderer.check_view(view)?;
    let device = &ctx.device;
    let (width, height) = renderer.size();
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let output = texture_2d(
        device,
        "splat image",
        (width, height),
        renderer.format,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
    );
    let output_view = output.create_view(&Default::default());
    let bound = renderer.bind_groups(device, view);
    let mut times = PassTimes::default();
    let run = |record: &dyn Fn(&mut wgpu::CommandEncoder)| -> Result<f64, GpuError> {
        let mut encoder = device.create_command_encoder(&Default::default());
        record(&mut encoder);
        let start = Instant::now();
        ctx.queue.submit([encoder.finish()]);
        crate::gpu::wait(device)?;
        Ok(start.elapsed().as_secs_f64() * 1e3)
    };
    times.visibility_ms = run(&|e| renderer.encode_visibility(e, surfels, &bound.splat))?;
    times.attributes_ms = run(&|e| renderer.encode_attributes(e, surfels, &bound.attributes))?;
    times.shading_ms = run(&|e| renderer.encode_shading(e, &output_view, &bound.shade))?;
    let image = gpu::read_texture(ctx, &output, 4)?;
    let colour = gpu::read_texture(ctx, &renderer.targets.colour, 16)?;
    let normal = gpu::read_texture(ctx, &renderer.targets.normal, 16)?;
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()).into());
    }
    let render = Render {
        width,
        height,
        image: image::RgbaImage::from_raw(width, height, image)
            .ok_or_else(|| GpuError::Readback("image of the wrong size".into()))?,
        colour: bytemuck::cast_slice(&colour).to_vec(),
        normal_depth: bytemuck::cast_slice(&normal).to_vec(),
    };
    render.validate().map_err(GpuError::Readback)?;
    Ok((render, times))
}

/// The uniforms of the three passes, as the shader reads them (`Uniforms` in the WGSL, 288 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawUniforms {
    pub view: [[f32; 4]; 4],
    pub proj: [[f32; 4]; 4],
    pub inv_view: [[f32; 4]; 4],
    pub viewport: [f32; 2],
    pub tan_half: [f32; 2],
    pub light_dir: [f32; 4],
    pub light_colour: [f32; 4],
    pub background: [f32; 4],
    pub material: [f32; 4],
    pub depth_offset: f32,
    pub low_pass: f32,
    pub sharpness: f32,
    pub mode: u32,
}

const _: () = assert!(std::mem::size_of::<RawUniforms>() == 288);

impl View {
    /// The shader's uniforms.
    #[must_use]
    pub fn to_raw(&self) -> RawUniforms {
        RawUniforms {
            view: self.view.to_cols_array_2d(),
            proj: self.proj.to_cols_array_2d(),
            inv_view: self.inv_view.to_cols_array_2d(),
            viewport: [self.width as f32, self.height as f32],
            tan_half: self.tan_half.to_array(),
            light_dir: self.light_dir.to_array(),
            light_colour: self.light_colour.to_array(),
            background: self.background.to_array(),
            material: [
                self.shininess,
                if self.orthographic { 1.0 } else { 0.0 },
                0.0,
                0.0,
            ],
            depth_offset: self.depth_offset,
            low_pass: self.low_pass,
            sharpness: self.sharpness,
            mode: match self.mode {
                SplatMode::Ewa => 0,
                SplatMode::Sprites => 1,
                SplatMode::Spheres => 2,
            },
        }
    }
}
