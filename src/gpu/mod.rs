//! The wgpu context shared by the GPU stages: headless (own adapter) or on a device the caller
//! already has (a game's), and the helpers they share (textures, bind-group entries, read-back).
//! Each stage's GPU twin lives beside its CPU path: [`crate::density::gpu`],
//! [`crate::splat::gpu`], [`crate::optics::gpu`], and the chain's [`crate::pipeline::GpuPipeline`].
//!
//! Shaders live in `shaders/*.wgsl` and are compiled into the crate; a unit test validates them
//! with naga.

pub mod timer;
pub use timer::TIMESTAMP_FEATURES;

use serde::Serialize;

/// Errors of the GPU stages.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    /// No adapter was found (no GPU and no software Vulkan driver such as Mesa's lavapipe).
    #[error(
        "no GPU adapter found ({0}); install a Vulkan driver (on Debian: apt-get install mesa-vulkan-drivers for lavapipe) or use the CPU path"
    )]
    NoAdapter(String),
    /// The adapter lacks a feature the stage needs.
    #[error("the GPU adapter `{adapter}` lacks {feature}")]
    MissingFeature {
        adapter: String,
        feature: &'static str,
    },
    /// The device could not be created.
    #[error("GPU device request failed: {0}")]
    Device(String),
    /// wgpu reported a validation or out-of-memory error.
    #[error("GPU error: {0}")]
    Validation(String),
    /// Reading results back failed.
    #[error("GPU readback failed: {0}")]
    Readback(String),
}

/// What adapter runs the GPU stages.
#[derive(Clone, Debug, Serialize)]
pub struct AdapterSummary {
    pub name: String,
    pub backend: String,
    pub device_type: String,
}

impl AdapterSummary {
    /// Whether the adapter is a software rasteriser (Mesa's lavapipe/llvmpipe, wgpu's
    /// `DeviceType::Cpu`): it proves the GPU path correct but runs it slower than the CPU path
    /// (measured in docs/design.md: the splatting renderers 1.3-3.2x, ray casting 38-94x;
    /// PLATFORM.md), so it is no
    /// default.
    #[must_use]
    pub fn is_software(&self) -> bool {
        self.device_type == format!("{:?}", wgpu::DeviceType::Cpu)
    }
}

/// A device and queue for the GPU stages.
#[derive(Clone, Debug)]
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// The adapter, when the context created it.
    pub adapter: Option<AdapterSummary>,
}

/// Features the GPU stages need: additive blending into `Rgba32Float` targets.
pub const REQUIRED_FEATURES: wgpu::Features = wgpu::Features::FLOAT32_BLENDABLE;

impl GpuContext {
    /// Creates its own device on the best adapter that has [`REQUIRED_FEATURES`]: of every
    /// adapter of the backends this build has (the crate's features `vulkan`, `metal`, `dx12`,
    /// `gles`; `WGPU_BACKEND` narrows them), a discrete GPU before an integrated, virtual or
    /// other one, a software rasteriser last, and in each kind Vulkan, Metal or DX12 before GL.
    /// When no adapter has the features, the error names the adapters and what they lack.
    pub fn headless() -> Result<Self, GpuError> {
        if wgpu::Instance::enabled_backend_features().is_empty() {
            return Err(GpuError::NoAdapter(
                "this build has no wgpu backend (features vulkan, metal, dx12, gles)".into(),
            ));
        }
        let descriptor = wgpu::InstanceDescriptor::new_without_display_handle().with_env();
        let backends = descriptor.backends;
        let instance = wgpu::Instance::new(descriptor);
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(wgpu::Adapter::get_info).collect();
        let candidates: Vec<(wgpu::DeviceType, wgpu::Backend, bool)> = adapters
            .iter()
            .zip(&infos)
            .map(|(a, i)| {
                (
                    i.device_type,
                    i.backend,
                    a.features().contains(REQUIRED_FEATURES),
                )
            })
            .collect();
        let Some(index) = pick_adapter(&candidates) else {
            return Err(if infos.is_empty() {
                GpuError::NoAdapter(format!("no adapter on the backends {backends:?}"))
            } else {
                GpuError::MissingFeature {
                    adapter: infos
                        .iter()
                        .map(|i| format!("{} ({:?})", i.name, i.backend))
                        .collect::<Vec<_>>()
                        .join(", "),
                    feature: "FLOAT32_BLENDABLE (additive blending into 32-bit float targets)",
                }
            });
        };
        let adapter = adapters
            .into_iter()
            .nth(index)
            .expect("an index of the list");
        let info = infos.into_iter().nth(index).expect("an index of the list");
        // the timestamps of `GpuPipeline::gpu_stage_ms` where the adapter has them
        let optional = adapter.features() & TIMESTAMP_FEATURES;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("fluid-surfels"),
            required_features: REQUIRED_FEATURES | optional,
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        Ok(Self {
            device,
            queue,
            adapter: Some(AdapterSummary {
                name: info.name,
                backend: format!("{:?}", info.backend),
                device_type: format!("{:?}", info.device_type),
            }),
        })
    }

    /// Uses a device the caller created (it must have [`REQUIRED_FEATURES`]).
    #[must_use]
    pub fn from_device(device: wgpu::Device, queue: wgpu::Queue) -> Self {
        Self {
            device,
            queue,
            adapter: None,
        }
    }
}

/// The index of the adapter [`GpuContext::headless`] takes among `(kind, backend, has the
/// required features)` per adapter, of those that have the features: the best device kind
/// (discrete, integrated, virtual, other, software), then Vulkan, Metal or DX12 before GL, then
/// the first listed. `None` when none has them.
#[must_use]
pub fn pick_adapter(adapters: &[(wgpu::DeviceType, wgpu::Backend, bool)]) -> Option<usize> {
    let kind = |t: wgpu::DeviceType| match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    };
    let backend = |b: wgpu::Backend| match b {
        wgpu::Backend::Vulkan | wgpu::Backend::Metal | wgpu::Backend::Dx12 => 0,
        _ => 1,
    };
    adapters
        .iter()
        .enumerate()
        .filter(|(_, a)| a.2)
        .min_by_key(|&(i, &(t, b, _))| (kind(t), backend(b), i))
        .map(|(i, _)| i)
}

/// The descriptor of a 2D texture of one mip level and one sample.
pub(crate) fn texture_descriptor(
    label: &str,
    (width, height): (u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::TextureDescriptor<'_> {
    wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage,
        view_formats: &[],
    }
}

/// The compute pipelines of `entries` in the WGSL `source`, each with the layout derived from
/// its entry point (so a pass's bind group holds exactly the bindings it uses).
pub(crate) fn compute_pipelines<const N: usize>(
    device: &wgpu::Device,
    label: &str,
    source: &str,
    entries: [&str; N],
) -> [wgpu::ComputePipeline; N] {
    compute_pipelines_with(device, (label, source), None, entries)
}

/// [`compute_pipelines`] with one `layout` for all of them (`None`: each its own, derived).
pub(crate) fn compute_pipelines_with<const N: usize>(
    device: &wgpu::Device,
    (label, source): (&str, &str),
    layout: Option<&wgpu::PipelineLayout>,
    entries: [&str; N],
) -> [wgpu::ComputePipeline; N] {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    entries.map(|entry| {
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout,
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        })
    })
}

/// A uniform buffer of `size` bytes, written through the queue.
pub(crate) fn uniform_buffer(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// The bind group of group 0 of `pipeline` from `(binding, resource)` pairs.
pub(crate) fn bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    entries: &[(u32, wgpu::BindingResource<'_>)],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
        .iter()
        .map(|(binding, resource)| wgpu::BindGroupEntry {
            binding: *binding,
            resource: resource.clone(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

/// The bind group of group 0 of `pipeline` binding each buffer whole at its binding.
pub(crate) fn buffer_bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    buffers: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let entries: Vec<(u32, wgpu::BindingResource<'_>)> = buffers
        .iter()
        .map(|&(binding, b)| (binding, b.as_entire_binding()))
        .collect();
    bind_group(device, pipeline, &entries)
}

/// A 2D texture of one mip level and one sample.
pub fn texture_2d(
    device: &wgpu::Device,
    label: &str,
    size: (u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    device.create_texture(&texture_descriptor(label, size, format, usage))
}

/// Bind group layout entries of the kinds the GPU stages use.
pub(crate) mod entry {
    /// A uniform buffer.
    pub(crate) fn uniform(
        binding: u32,
        visibility: wgpu::ShaderStages,
    ) -> wgpu::BindGroupLayoutEntry {
        buffer(binding, visibility, wgpu::BufferBindingType::Uniform)
    }

    /// A read-write storage buffer.
    pub(crate) fn storage(
        binding: u32,
        visibility: wgpu::ShaderStages,
    ) -> wgpu::BindGroupLayoutEntry {
        buffer(
            binding,
            visibility,
            wgpu::BufferBindingType::Storage { read_only: false },
        )
    }

    /// A read-only storage buffer.
    pub(crate) fn read_only(
        binding: u32,
        visibility: wgpu::ShaderStages,
    ) -> wgpu::BindGroupLayoutEntry {
        buffer(
            binding,
            visibility,
            wgpu::BufferBindingType::Storage { read_only: true },
        )
    }

    fn buffer(
        binding: u32,
        visibility: wgpu::ShaderStages,
        ty: wgpu::BufferBindingType,
    ) -> wgpu::BindGroupLayoutEntry {
        wgpu::BindGroupLayoutEntry {
            binding,
            visibility,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }
    }

    /// A non-filterable float 2D texture (read with `textureLoad`).
    pub(crate) fn texture(
        binding: u32,
        visibility: wgpu::ShaderStages,
    ) -> wgpu::BindGroupLayoutEntry {
        wgpu::BindGroupLayoutEntry {
            binding,
            visibility,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        }
    }
}

/// Maps `slice` of a `MAP_READ` buffer for reading and waits until it is mapped (the work
/// submitted before it included).
pub(crate) fn map_read_and_wait(
    device: &wgpu::Device,
    slice: &wgpu::BufferSlice<'_>,
) -> Result<(), GpuError> {
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    wait(device)?;
    rx.recv()
        .map_err(|e| GpuError::Readback(e.to_string()))?
        .map_err(|e| GpuError::Readback(e.to_string()))
}

/// Copies a 2D texture back, rows unpadded (`texel_bytes` per texel): the one read-back of
/// textures that every GPU stage, the CLI and the tests use.
pub fn read_texture(
    ctx: &GpuContext,
    texture: &wgpu::Texture,
    texel_bytes: u32,
) -> Result<Vec<u8>, GpuError> {
    let (width, height) = (texture.width(), texture.height());
    let row = width * texel_bytes;
    let padded =
        row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("texture readback"),
        size: u64::from(padded) * u64::from(height),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded),
                rows_per_image: Some(height),
            },
        },
        texture.size(),
    );
    ctx.queue.submit([encoder.finish()]);
    let slice = buffer.slice(..);
    map_read_and_wait(&ctx.device, &slice)?;
    let data = slice
        .get_mapped_range()
        .map_err(|e| GpuError::Readback(format!("{e:?}")))?;
    let mut out = Vec::with_capacity((row * height) as usize);
    for y in 0..height as usize {
        let start = y * padded as usize;
        out.extend_from_slice(&data[start..start + row as usize]);
    }
    drop(data);
    buffer.unmap();
    Ok(out)
}

/// Copies a whole buffer (`COPY_SRC`) back as values of `T`: the buffers' read-back, beside
/// [`read_texture`] for textures.
pub fn read_buffer<T: bytemuck::Pod>(
    ctx: &GpuContext,
    buffer: &wgpu::Buffer,
) -> Result<Vec<T>, GpuError> {
    let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("buffer readback"),
        size: buffer.size(),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, buffer.size());
    ctx.queue.submit([encoder.finish()]);
    let slice = staging.slice(..);
    map_read_and_wait(&ctx.device, &slice)?;
    let data = slice
        .get_mapped_range()
        .map_err(|e| GpuError::Readback(format!("{e:?}")))?;
    let out = bytemuck::cast_slice(&data).to_vec();
    drop(data);
    staging.unmap();
    Ok(out)
}

/// Reads an 8-bit RGBA texture (`Rgba8Unorm` or `Rgba8UnormSrgb`, the stored bytes) back as an
/// image.
pub fn read_rgba8(ctx: &GpuContext, texture: &wgpu::Texture) -> Result<image::RgbaImage, GpuError> {
    let bytes = read_texture(ctx, texture, 4)?;
    image::RgbaImage::from_raw(texture.width(), texture.height(), bytes)
        .ok_or_else(|| GpuError::Readback("texture size does not match its bytes".into()))
}

/// For tests and benchmarks: a headless context, or `None` with a message on stderr when there
/// is no adapter. With `FLUID_SURFELS_REQUIRE_GPU=1` a missing adapter is an error instead.
pub fn context_or_skip(what: &str) -> Result<Option<GpuContext>, GpuError> {
    match GpuContext::headless() {
        Ok(c) => {
            if let Some(a) = &c.adapter {
                eprintln!(
                    "{what}: GPU adapter {} ({}, {})",
                    a.name, a.backend, a.device_type
                );
            }
            Ok(Some(c))
        }
        Err(e) if std::env::var("FLUID_SURFELS_REQUIRE_GPU").is_ok_and(|v| v == "1") => Err(e),
        Err(e) => {
            eprintln!(
                "{what}: SKIPPED, no usable GPU adapter ({e}); set FLUID_SURFELS_REQUIRE_GPU=1 to make this an error"
            );
            Ok(None)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::pick_adapter;
    use wgpu::{Backend, DeviceType};

    /// The headless context's choice: features first, then the device kind, then the backend,
    /// then the order listed; none when no adapter has the features.
    #[test]
    fn adapter_choice_prefers_features_then_kind_then_native_backends() {
        assert_eq!(pick_adapter(&[]), None);
        assert_eq!(
            pick_adapter(&[(DeviceType::DiscreteGpu, Backend::Vulkan, false)]),
            None
        );
        // a software Vulkan (lavapipe) before a GL software rasteriser
        let software = [
            (DeviceType::Cpu, Backend::Gl, true),
            (DeviceType::Cpu, Backend::Vulkan, true),
        ];
        assert_eq!(pick_adapter(&software), Some(1));
        // a discrete GPU without the features loses to an integrated one with them
        let mixed = [
            (DeviceType::DiscreteGpu, Backend::Vulkan, false),
            (DeviceType::Cpu, Backend::Vulkan, true),
            (DeviceType::IntegratedGpu, Backend::Gl, true),
            (DeviceType::IntegratedGpu, Backend::Metal, true),
        ];
        assert_eq!(pick_adapter(&mixed), Some(3));
        // ties keep the order listed
        let twins = [
            (DeviceType::DiscreteGpu, Backend::Dx12, true),
            (DeviceType::DiscreteGpu, Backend::Vulkan, true),
        ];
        assert_eq!(pick_adapter(&twins), Some(0));
    }
}

thread_local! {
    /// Waits on the device by this crate on this thread ([`waits`]).
    static WAITS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// How many times this crate has waited on a device (a blocking poll: every read-back and
/// every timing) on the calling thread: a test of a frame path reads it before and after the
/// frames and finds it unchanged (issue 37).
#[must_use]
pub fn waits() -> usize {
    WAITS.with(std::cell::Cell::get)
}

/// The largest storage buffer a pass can bind on `device` (its binding and buffer limits).
pub(crate) fn max_binding(device: &wgpu::Device) -> u64 {
    let limits = device.limits();
    limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size)
}

/// Waits until the device has done the work submitted to it, counted in [`waits`].
pub(crate) fn wait(device: &wgpu::Device) -> Result<(), GpuError> {
    WAITS.with(|w| w.set(w.get() + 1));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map(|_| ())
        .map_err(|e| GpuError::Readback(e.to_string()))
}

/// A colour attachment of `view` cleared to transparent black and stored.
pub(crate) fn cleared(view: &wgpu::TextureView) -> Option<wgpu::RenderPassColorAttachment<'_>> {
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
            store: wgpu::StoreOp::Store,
        },
    })
}

/// A bind group of `layout` binding each of `buffers` whole at its index.
pub(crate) fn buffers_bind_group(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    buffers: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: b.as_entire_binding(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
}

/// A buffer kept from frame to frame that grows when a frame needs more (by half again, so
/// that a slowly growing need makes few new buffers) and is otherwise rewritten in place.
pub(crate) struct Grow {
    label: &'static str,
    usage: wgpu::BufferUsages,
    buffer: Option<wgpu::Buffer>,
}

impl Grow {
    pub(crate) fn new(label: &'static str, usage: wgpu::BufferUsages) -> Self {
        Self {
            label,
            usage: usage | wgpu::BufferUsages::COPY_DST,
            buffer: None,
        }
    }

    /// Makes sure the buffer holds `size` bytes (at least 32: one element of the largest
    /// runtime array bound, the compute passes' 32-byte points); whether a new one was made.
    pub(crate) fn reserve(&mut self, device: &wgpu::Device, size: u64) -> bool {
        let size = size.max(32).next_multiple_of(4);
        if self.buffer.as_ref().is_some_and(|b| b.size() >= size) {
            return false;
        }
        let grown = self
            .buffer
            .as_ref()
            .map_or(size, |b| size.max(b.size() / 2 * 3));
        self.buffer = Some(device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(self.label),
            size: grown.next_multiple_of(4),
            usage: self.usage,
            mapped_at_creation: false,
        }));
        true
    }

    /// Writes `bytes` at the start (through the queue: it takes effect at the next submit),
    /// growing first when they do not fit; whether a new buffer was made.
    pub(crate) fn write(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        bytes: &[u8],
    ) -> bool {
        let made = self.reserve(device, bytes.len() as u64);
        if !bytes.is_empty() {
            queue.write_buffer(self.buffer(), 0, bytes);
        }
        made
    }

    /// The buffer ([`Self::reserve`] or [`Self::write`] first).
    pub(crate) fn buffer(&self) -> &wgpu::Buffer {
        self.buffer.as_ref().expect("reserved before use")
    }
}

/// Writes each byte slice of `writes` into its buffer ([`Grow::write`]); how many buffers were
/// made anew (the bind groups holding them are stale then).
pub(crate) fn write_grown<const N: usize>(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    writes: [(&mut Grow, &[u8]); N],
) -> usize {
    writes
        .into_iter()
        .map(|(grow, bytes)| usize::from(grow.write(device, queue, bytes)))
        .sum()
}

/// A small buffer read back without a wait (issue 37): a copy recorded into a frame's encoder
/// when no read is under way, mapped once that encoder is submitted
/// ([`AsyncRead::after_submit`]), and its bytes taken by a later frame once the map is done (a
/// few frames late: the caller's submits and presents poll the device). Nothing waits.
pub(crate) struct AsyncRead {
    buffer: wgpu::Buffer,
    state: ReadState,
}

/// Where an [`AsyncRead`] stands: a copy recorded this frame, a mapping started after the
/// submit (its result set by the callback), or neither.
enum ReadState {
    Idle,
    Copied,
    Mapping(std::sync::Arc<std::sync::Mutex<Option<Result<(), wgpu::BufferAsyncError>>>>),
}

impl AsyncRead {
    /// A read-back buffer of `size` bytes.
    pub(crate) fn new(device: &wgpu::Device, label: &'static str, size: u64) -> Self {
        Self {
            buffer: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            state: ReadState::Idle,
        }
    }

    /// Records a copy of the buffer's size from `source` at `offset` into `encoder` when no read
    /// is under way; whether it did.
    pub(crate) fn copy(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        source: &wgpu::Buffer,
        offset: u64,
    ) -> bool {
        if !matches!(self.state, ReadState::Idle) {
            return false;
        }
        encoder.copy_buffer_to_buffer(source, offset, &self.buffer, 0, self.buffer.size());
        self.state = ReadState::Copied;
        true
    }

    /// Starts the mapping of a copy recorded into an encoder that is now submitted.
    pub(crate) fn after_submit(&mut self) {
        if matches!(self.state, ReadState::Copied) {
            let done = std::sync::Arc::new(std::sync::Mutex::new(None));
            let set = std::sync::Arc::clone(&done);
            self.buffer
                .slice(..)
                .map_async(wgpu::MapMode::Read, move |r| {
                    if let Ok(mut d) = set.lock() {
                        *d = Some(r);
                    }
                });
            self.state = ReadState::Mapping(done);
        }
    }

    /// The bytes of a finished read, if one has finished (a failed one gives nothing); a new
    /// copy may then be recorded.
    pub(crate) fn take(&mut self) -> Option<Vec<u8>> {
        let ReadState::Mapping(done) = &self.state else {
            return None;
        };
        let result = done.lock().ok().and_then(|mut d| d.take())?;
        let bytes = match result {
            Ok(()) => {
                let bytes = self
                    .buffer
                    .slice(..)
                    .get_mapped_range()
                    .ok()
                    .map(|data| data.to_vec());
                self.buffer.unmap();
                bytes
            }
            Err(_) => None,
        };
        self.state = ReadState::Idle;
        bytes
    }
}
