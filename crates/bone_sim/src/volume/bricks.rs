//! Copy-on-write material bricks: what one session has drilled out of a shared volume.
//!
//! The grid is tiled into 8³ bricks. A session owns a brick only once it has eroded something in
//! it; every other voxel reads the shared pristine material. Memory is therefore proportional to
//! what was drilled (1 KiB per touched brick plus a 4-byte table entry per brick of the grid), and
//! reset is O(touched bricks).

use super::grid::Grid;
use super::Volume;

/// Voxels along one brick edge (a power of two).
pub const BRICK_EDGE: usize = 8;
const BRICK_SHIFT: usize = 3;
const BRICK_MASK: usize = BRICK_EDGE - 1;
/// Voxels in one brick.
pub const BRICK_VOXELS: usize = BRICK_EDGE * BRICK_EDGE * BRICK_EDGE;
const NO_BRICK: u32 = u32::MAX;

/// Material fractions (`u16`, 65535 = full) of one brick, local index `(lk·8 + lj)·8 + li`.
pub type Brick = [u16; BRICK_VOXELS];

/// A session's private copies of the bricks it has drilled.
#[derive(Debug)]
pub struct MaterialOverlay {
    bricks_per_axis: [usize; 3],
    /// Brick id → slot in `slots`, or `NO_BRICK`.
    table: Vec<u32>,
    slots: Vec<Brick>,
    /// Slot → brick id (the touched list that makes reset cheap).
    slot_brick: Vec<u32>,
}

/// A clone keeps the original's reserved room (a derived `Clone` would not: `Vec::clone` allocates
/// only the length), so a cloned overlay is as allocation-free as the original. The engine's
/// snapshot buffers are clones.
impl Clone for MaterialOverlay {
    fn clone(&self) -> Self {
        let mut slots = Vec::with_capacity(self.slots.capacity());
        slots.extend_from_slice(&self.slots);
        let mut slot_brick = Vec::with_capacity(self.slot_brick.capacity());
        slot_brick.extend_from_slice(&self.slot_brick);
        Self { bricks_per_axis: self.bricks_per_axis, table: self.table.clone(), slots, slot_brick }
    }
}

impl MaterialOverlay {
    /// An empty overlay for `grid`, with room for `reserve_bricks` bricks before it allocates.
    #[must_use]
    pub fn new(grid: &Grid, reserve_bricks: usize) -> Self {
        let bricks_per_axis = grid.dims().map(|d| d.div_ceil(BRICK_EDGE));
        let count = bricks_per_axis.iter().product();
        Self {
            bricks_per_axis,
            table: vec![NO_BRICK; count],
            slots: Vec::with_capacity(reserve_bricks),
            slot_brick: Vec::with_capacity(reserve_bricks),
        }
    }

    /// Makes this overlay a copy of `other` (same grid), reusing this one's buffers: no
    /// allocation while `other` holds no more bricks than this overlay has reserved.
    pub fn copy_from(&mut self, other: &Self) {
        debug_assert_eq!(self.table.len(), other.table.len(), "overlays of different grids");
        self.table.copy_from_slice(&other.table);
        self.slots.clear();
        self.slots.extend_from_slice(&other.slots);
        self.slot_brick.clear();
        self.slot_brick.extend_from_slice(&other.slot_brick);
    }

    /// Brick id of voxel (i, j, k).
    #[inline]
    #[must_use]
    pub fn brick_id(&self, i: usize, j: usize, k: usize) -> usize {
        ((k >> BRICK_SHIFT) * self.bricks_per_axis[1] + (j >> BRICK_SHIFT)) * self.bricks_per_axis[0]
            + (i >> BRICK_SHIFT)
    }

    /// Index of voxel (i, j, k) inside its brick.
    #[inline]
    #[must_use]
    pub fn local(i: usize, j: usize, k: usize) -> usize {
        (((k & BRICK_MASK) << BRICK_SHIFT) + (j & BRICK_MASK)) << BRICK_SHIFT | (i & BRICK_MASK)
    }

    /// First voxel (i, j, k) of a brick.
    #[must_use]
    pub fn brick_origin(&self, brick_id: usize) -> [usize; 3] {
        let bx = brick_id % self.bricks_per_axis[0];
        let by = (brick_id / self.bricks_per_axis[0]) % self.bricks_per_axis[1];
        let bz = brick_id / (self.bricks_per_axis[0] * self.bricks_per_axis[1]);
        [bx << BRICK_SHIFT, by << BRICK_SHIFT, bz << BRICK_SHIFT]
    }

    /// The session's brick for a brick id, if it has one.
    #[inline]
    #[must_use]
    pub fn brick(&self, brick_id: usize) -> Option<&Brick> {
        match self.table[brick_id] {
            NO_BRICK => None,
            slot => Some(&self.slots[slot as usize]),
        }
    }

    /// Current material of voxel (i, j, k) (inside the grid).
    #[inline]
    #[must_use]
    pub fn material(&self, volume: &Volume, i: usize, j: usize, k: usize) -> u16 {
        match self.brick(self.brick_id(i, j, k)) {
            Some(brick) => brick[Self::local(i, j, k)],
            None => volume.pristine_material(volume.grid().linear(i, j, k)),
        }
    }

    /// The material of the 2 × 2 × 2 voxels from (i, j, k) to (i + 1, j + 1, k + 1), as
    /// `[dk][dj][di]`: a trilinear read's cell, which must lie inside the grid. Equal to eight
    /// [`material`](Self::material) calls, with one brick lookup where the cell lies in one brick.
    #[inline]
    #[must_use]
    pub fn cell(&self, volume: &Volume, i: usize, j: usize, k: usize) -> [[[u16; 2]; 2]; 2] {
        let within = (i & BRICK_MASK) != BRICK_MASK && (j & BRICK_MASK) != BRICK_MASK && (k & BRICK_MASK) != BRICK_MASK;
        if !within {
            let m = |di: usize, dj: usize, dk: usize| self.material(volume, i + di, j + dj, k + dk);
            return [
                [[m(0, 0, 0), m(1, 0, 0)], [m(0, 1, 0), m(1, 1, 0)]],
                [[m(0, 0, 1), m(1, 0, 1)], [m(0, 1, 1), m(1, 1, 1)]],
            ];
        }
        if let Some(brick) = self.brick(self.brick_id(i, j, k)) {
            // Steps along i, j and k in a brick (local index (lk·8 + lj)·8 + li).
            let (si, sj, sk) = (1, BRICK_EDGE, BRICK_EDGE * BRICK_EDGE);
            let b = &brick[Self::local(i, j, k)..=Self::local(i, j, k) + sk + sj + si];
            [[[b[0], b[si]], [b[sj], b[sj + si]]], [[b[sk], b[sk + si]], [b[sk + sj], b[sk + sj + si]]]]
        } else {
            // The same steps in the volume.
            let dims = volume.grid().dims();
            let (sj, sk) = (dims[0], dims[0] * dims[1]);
            let l = volume.grid().linear(i, j, k);
            let p = |o: usize| volume.pristine_material(l + o);
            [[[p(0), p(1)], [p(sj), p(sj + 1)]], [[p(sk), p(sk + 1)], [p(sk + sj), p(sk + sj + 1)]]]
        }
    }

    /// The session's own copy of a brick, made from the pristine volume on first write.
    /// Allocates only when more bricks are touched than were reserved.
    pub fn brick_mut(&mut self, volume: &Volume, brick_id: usize) -> &mut Brick {
        let slot = match self.table[brick_id] {
            NO_BRICK => {
                let slot = self.slots.len();
                self.slots.push(self.pristine_brick(volume, brick_id));
                self.slot_brick.push(brick_id as u32);
                self.table[brick_id] = slot as u32;
                slot
            }
            slot => slot as usize,
        };
        &mut self.slots[slot]
    }

    fn pristine_brick(&self, volume: &Volume, brick_id: usize) -> Brick {
        let mut brick = [0u16; BRICK_VOXELS];
        let [i0, j0, k0] = self.brick_origin(brick_id);
        let dims = volume.grid().dims();
        for k in k0..(k0 + BRICK_EDGE).min(dims[2]) {
            for j in j0..(j0 + BRICK_EDGE).min(dims[1]) {
                for i in i0..(i0 + BRICK_EDGE).min(dims[0]) {
                    brick[Self::local(i, j, k)] = volume.pristine_material(volume.grid().linear(i, j, k));
                }
            }
        }
        brick
    }

    /// Every brick this session owns, as (brick id, brick).
    pub fn owned(&self) -> impl Iterator<Item = (usize, &Brick)> {
        self.slot_brick.iter().zip(&self.slots).map(|(&id, b)| (id as usize, b))
    }

    /// Number of bricks this session owns.
    #[must_use]
    pub fn owned_count(&self) -> usize {
        self.slots.len()
    }

    /// Forgets every edit: O(owned bricks), keeps the reserved capacity.
    pub fn reset(&mut self) {
        for &id in &self.slot_brick {
            self.table[id as usize] = NO_BRICK;
        }
        self.slots.clear();
        self.slot_brick.clear();
    }

    /// Heap bytes this overlay holds (table plus brick slots, by capacity).
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        self.table.capacity() * 4
            + self.slots.capacity() * std::mem::size_of::<Brick>()
            + self.slot_brick.capacity() * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::layer::Layer;
    use crate::volume::test_support::uniform_block;
    use crate::volume::FULL_MATERIAL;

    #[test]
    fn copy_on_write_and_reset() {
        let v = uniform_block(20, 1e-3, Layer::Cortical, 1500.0, 2);
        let mut o = MaterialOverlay::new(v.grid(), 0);
        assert_eq!(o.material(&v, 5, 5, 5), FULL_MATERIAL);
        assert_eq!(o.material(&v, 0, 0, 0), 0);
        let id = o.brick_id(5, 5, 5);
        o.brick_mut(&v, id)[MaterialOverlay::local(5, 5, 5)] = 7;
        assert_eq!(o.material(&v, 5, 5, 5), 7);
        // The rest of the copied brick keeps the pristine values, including air at the margin.
        assert_eq!(o.material(&v, 4, 5, 5), FULL_MATERIAL);
        assert_eq!(o.material(&v, 1, 5, 5), 0);
        assert_eq!(o.owned_count(), 1);
        o.reset();
        assert_eq!(o.owned_count(), 0);
        assert_eq!(o.material(&v, 5, 5, 5), FULL_MATERIAL);
    }

    #[test]
    fn edge_bricks_past_the_grid_hold_no_material() {
        // 20 is not a multiple of 8: the last brick hangs over the grid's edge.
        let v = uniform_block(20, 1e-3, Layer::Cortical, 1500.0, 0);
        let mut o = MaterialOverlay::new(v.grid(), 0);
        let id = o.brick_id(19, 19, 19);
        let brick = *o.brick_mut(&v, id);
        assert_eq!(brick[MaterialOverlay::local(19, 19, 19)], FULL_MATERIAL);
        assert_eq!(brick[MaterialOverlay::local(20, 19, 19)], 0);
        assert_eq!(o.brick_origin(id), [16, 16, 16]);
    }

    #[test]
    fn a_cell_reads_what_eight_voxel_reads_give_across_brick_edges_and_drilled_bricks() {
        // 20 voxels a side: cells inside one brick, across brick edges and in the hanging last
        // brick; margin 3, so pristine air and bone both appear; two bricks drilled with values
        // that differ voxel by voxel, so a wrong step or a swapped axis shows.
        let v = uniform_block(20, 1e-3, Layer::Cortical, 1500.0, 3);
        let mut o = MaterialOverlay::new(v.grid(), 0);
        for (bi, bj, bk) in [(5, 5, 5), (9, 4, 12)] {
            let id = o.brick_id(bi, bj, bk);
            for (n, m) in o.brick_mut(&v, id).iter_mut().enumerate() {
                *m = (n as u16).wrapping_mul(97);
            }
        }
        for k in 0..19 {
            for j in 0..19 {
                for i in 0..19 {
                    let c = o.cell(&v, i, j, k);
                    for (dk, plane) in c.iter().enumerate() {
                        for (dj, row) in plane.iter().enumerate() {
                            for (di, &m) in row.iter().enumerate() {
                                let at = (i + di, j + dj, k + dk);
                                assert_eq!(
                                    m,
                                    o.material(&v, at.0, at.1, at.2),
                                    "cell ({i}, {j}, {k}) + ({di}, {dj}, {dk})"
                                );
                            }
                        }
                    }
                }
            }
        }
    }
}
