//! Which points of a grid plane are inside the iso-surface, one bit each: the scans of the
//! surfels' crossings ([`crate::surfels::SurfelExtractor`]) and of the mesh's cubes
//! ([`crate::mesh::cubes`]) find the crossing edges with a few word operations per 64 points,
//! where most of a grid is far from the surface (reading eight corners a cube, the 150k
//! block's 85^3 grid took 12 ms to mesh; comparing each edge's two values, the dam break's
//! 174 x 223 x 94 grid at two steps took 21 ms to scan for surfels on one thread).

/// Which points of a plane are inside (not below the iso-value: `1 - (v < iso)`, so that a NaN
/// value reads as inside, as the comparisons of the edge-by-edge scans read it), one bit each,
/// row by row (`words` words a row, bit `i % 64` of word `i / 64` for point `i`; bits past the
/// row's end 0).
pub(crate) struct Bits {
    pub(crate) words: usize,
    bits: Vec<u64>,
}

impl Bits {
    /// The bits of `plane` (rows of `nx` values).
    pub(crate) fn of(plane: &[f32], nx: u32, iso: f32) -> Self {
        let words = (nx as usize).div_ceil(64);
        let mut bits = Vec::with_capacity(words * plane.len() / nx.max(1) as usize);
        // a byte per point first, then each 8 bytes of 0 or 1 gathered into 8 bits by one
        // multiplication (byte `k` times `2^(7 - m)` at byte `m` lands at bit 56 + k for
        // `k + m = 7`): the comparisons vectorise, where shifting each point's bit into its
        // word did not (174 x 223 x 94 points: 4.2-7.3 -> 1.1 ms on one core)
        let mut bytes = [0u8; 64];
        for row in plane.chunks_exact(nx as usize) {
            for chunk in row.chunks(64) {
                bytes.fill(0);
                for (b, &v) in bytes.iter_mut().zip(chunk) {
                    *b = 1 - u8::from(v < iso);
                }
                let mut w = 0u64;
                for (g, eight) in bytes.chunks_exact(8).enumerate() {
                    let x = u64::from_le_bytes(eight.try_into().expect("8 bytes"));
                    w |= (x.wrapping_mul(0x0102_0408_1020_4080) >> 56) << (8 * g);
                }
                bits.push(w);
            }
        }
        Self { words, bits }
    }

    /// Row `j`'s words.
    pub(crate) fn row(&self, j: u32) -> &[u64] {
        &self.bits[j as usize * self.words..(j as usize + 1) * self.words]
    }
}

/// Word `w` of a row shifted down by one point (bit `i` holds point `i + 1`).
pub(crate) fn next_point(row: &[u64], w: usize) -> u64 {
    (row[w] >> 1) | row.get(w + 1).map_or(0, |&n| n << 63)
}

/// The bits of word `w` for points below `end`.
pub(crate) fn below(w: usize, end: u32) -> u64 {
    let first = 64 * w as u32;
    match end.saturating_sub(first) {
        0 => 0,
        n if n >= 64 => u64::MAX,
        n => (1u64 << n) - 1,
    }
}

/// The set bits of `mask`, as points of word `w`, in increasing order.
pub(crate) fn points_of(mut mask: u64, w: usize) -> impl Iterator<Item = u32> {
    std::iter::from_fn(move || {
        (mask != 0).then(|| {
            let b = mask.trailing_zeros();
            mask &= mask - 1;
            64 * w as u32 + b
        })
    })
}
