//! GPU time per stage of a frame, and per pass within a stage, by timestamp queries (issue 37),
//! where the device has [`TIMESTAMP_FEATURES`]: timestamps written into the frame's encoder
//! between its stages and passes, resolved and copied into a buffer that is read back without a
//! wait (`gpu::AsyncRead`), so that the times arrive a few frames late and nothing on the frame
//! path waits.
//!
//! On lavapipe a timestamp does not wait for the dispatches before it: a pass's last dispatch
//! runs on while the timestamp after it is written and is counted in the next interval whose
//! work waits on it (measured: three targets dispatches instead of one raised the targets'
//! interval from 5.9 to 468 ms while the next one, the compaction's, stayed 320-349 ms). A
//! conformant GPU writes a timestamp once the work before it is done.

use super::AsyncRead;

/// The features the stage timer of `GpuPipeline::time_stages` needs (requested by
/// [`super::GpuContext::headless`] where the adapter has them; a game asks for them on its own
/// device).
pub const TIMESTAMP_FEATURES: wgpu::Features =
    wgpu::Features::TIMESTAMP_QUERY.union(wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS);

/// Timestamps a frame may write.
const MARKS: u32 = 32;

/// A timestamp of a frame: the end of stage `i` (written in order, 0 first: the frame's start),
/// or the end of a pass within a stage, by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Mark {
    Stage(u32),
    Pass(&'static str),
}

/// Timestamps between the stages of a frame, and between passes within them. See the module
/// documentation.
pub(crate) struct StageTimer {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: AsyncRead,
    /// Nanoseconds per tick.
    period_ns: f64,
    /// The timestamps written this frame.
    marks: Vec<Mark>,
    /// The stage marks written this frame (the next stage mark's index).
    stages: u32,
    /// The marks of the frame whose copy is being read back.
    copied: Option<Vec<Mark>>,
    /// The marks and ticks of the last frame read back.
    last: Option<Vec<(Mark, u64)>>,
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
            marks: Vec::new(),
            stages: 0,
            copied: None,
            last: None,
        })
    }

    /// Starts a frame: takes the ticks of a read that has finished.
    pub(crate) fn begin(&mut self) {
        if let Some(bytes) = self.read.take() {
            let ticks: Vec<u64> = bytemuck::pod_collect_to_vec(&bytes);
            self.last = self
                .copied
                .take()
                .map(|marks| marks.into_iter().zip(ticks).collect());
        }
        self.marks.clear();
        self.stages = 0;
    }

    /// Writes one timestamp (none past [`MARKS`]).
    fn write(&mut self, encoder: &mut wgpu::CommandEncoder, mark: Mark) {
        if (self.marks.len() as u32) < MARKS {
            encoder.write_timestamp(&self.set, self.marks.len() as u32);
            self.marks.push(mark);
        }
    }

    /// Writes the stage timestamps up to `index` (0-based) that this frame has not written yet.
    pub(crate) fn mark_to(&mut self, encoder: &mut wgpu::CommandEncoder, index: u32) {
        while self.stages <= index {
            self.write(encoder, Mark::Stage(self.stages));
            self.stages += 1;
        }
    }

    /// Writes a timestamp at the end of the pass `name` within the current stage.
    pub(crate) fn mark_pass(&mut self, encoder: &mut wgpu::CommandEncoder, name: &'static str) {
        self.write(encoder, Mark::Pass(name));
    }

    /// Ends a frame: resolves its timestamps and records their copy, when no read is under way.
    pub(crate) fn end(&mut self, encoder: &mut wgpu::CommandEncoder) {
        let count = self.marks.len() as u32;
        if count < 2 {
            return;
        }
        encoder.resolve_query_set(&self.set, 0..count, &self.resolve, 0);
        if self.read.copy(encoder, &self.resolve, 0) {
            self.copied = Some(self.marks.clone());
        }
    }

    /// Starts the read-back of the frame just submitted.
    pub(crate) fn after_submit(&mut self) {
        self.read.after_submit();
    }

    /// Milliseconds between consecutive stage timestamps of the last frame read back (`stages
    /// - 1` of them when it wrote the stage marks 0 to `stages - 1`).
    pub(crate) fn last_ms(&self, stages: usize) -> Option<Vec<f64>> {
        let ticks: Vec<u64> = self
            .last
            .as_ref()?
            .iter()
            .filter(|(m, _)| matches!(m, Mark::Stage(_)))
            .map(|&(_, t)| t)
            .collect();
        (ticks.len() >= stages).then(|| {
            ticks[..stages]
                .windows(2)
                .map(|w| self.ms(w[1], w[0]))
                .collect()
        })
    }

    /// Every timestamp of the last frame read back after its first, with the milliseconds since
    /// the one before it.
    pub(crate) fn last_marks(&self) -> Option<Vec<(Mark, f64)>> {
        let last = self.last.as_ref()?;
        Some(
            last.windows(2)
                .map(|w| (w[1].0, self.ms(w[1].1, w[0].1)))
                .collect(),
        )
    }

    /// Milliseconds from tick `from` to tick `to` (0 when the clock ran backwards).
    fn ms(&self, to: u64, from: u64) -> f64 {
        to.saturating_sub(from) as f64 * self.period_ns * 1e-6
    }
}
