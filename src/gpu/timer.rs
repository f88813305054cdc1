//! GPU time per stage of a frame by timestamp queries (issue 37), where the device has
//! [`TIMESTAMP_FEATURES`]: timestamps written into the frame's encoder between its stages,
//! resolved and copied into a buffer that is read back without a wait (`gpu::AsyncRead`),
//! so that the times arrive a few frames late and nothing on the frame path waits.

use super::AsyncRead;

/// The features the stage timer of `GpuPipeline::time_stages` needs (requested by
/// [`super::GpuContext::headless`] where the adapter has them; a game asks for them on its own
/// device).
pub const TIMESTAMP_FEATURES: wgpu::Features =
    wgpu::Features::TIMESTAMP_QUERY.union(wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS);

/// Timestamps a frame may write.
const MARKS: u32 = 8;

/// Timestamps between the stages of a frame. See the module documentation.
pub(crate) struct StageTimer {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: AsyncRead,
    /// Nanoseconds per tick.
    period_ns: f64,
    /// Timestamps written this frame.
    marks: u32,
    /// The ticks of the last frame read back.
    last: Option<Vec<u64>>,
}

impl StageTimer {
    /// A timer for `device`; `None` when it lacks [`TIMESTAMP_FEATURES`].
    pub(crate) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Option<Self> {
        if !device.features().contains(TIMESTAMP_FEATURES) {
            return None;
        }
        let bytes = u64::from(MARKS) * 8;
        Some(Self {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("stage timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: MARKS,
            }),
            resolve: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("stage timestamps resolved"),
                size: bytes,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            read: AsyncRead::new(device, "stage timestamps read", bytes),
            period_ns: f64::from(queue.get_timestamp_period()),
            marks: 0,
            last: None,
        })
    }

    /// Starts a frame: takes the ticks of a read that has finished.
    pub(crate) fn begin(&mut self) {
        if let Some(bytes) = self.read.take() {
            self.last = Some(bytemuck::pod_collect_to_vec(&bytes));
        }
        self.marks = 0;
    }

    /// Writes the timestamps up to `index` (0-based) that this frame has not written yet.
    pub(crate) fn mark_to(&mut self, encoder: &mut wgpu::CommandEncoder, index: u32) {
        while self.marks <= index.min(MARKS - 1) {
            encoder.write_timestamp(&self.set, self.marks);
            self.marks += 1;
        }
    }

    /// Ends a frame: resolves its timestamps and records their copy, when no read is under way.
    pub(crate) fn end(&mut self, encoder: &mut wgpu::CommandEncoder) {
        if self.marks < 2 {
            return;
        }
        encoder.resolve_query_set(&self.set, 0..self.marks, &self.resolve, 0);
        self.read.copy(encoder, &self.resolve, 0);
    }

    /// Starts the read-back of the frame just submitted.
    pub(crate) fn after_submit(&mut self) {
        self.read.after_submit();
    }

    /// Milliseconds between consecutive timestamps of the last frame read back (`marks - 1`
    /// of them for the frame's `marks` timestamps).
    pub(crate) fn last_ms(&self, marks: usize) -> Option<Vec<f64>> {
        let ticks = self.last.as_ref()?;
        (ticks.len() >= marks).then(|| {
            ticks[..marks]
                .windows(2)
                .map(|w| w[1].saturating_sub(w[0]) as f64 * self.period_ns * 1e-6)
                .collect()
        })
    }
}
