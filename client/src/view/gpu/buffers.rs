//! What the shaders read, byte for byte (`#[repr(C)]`, matching the structs of `shaders.wgsl`),
//! and the buffers that hold it: a mesh uploaded once ([`GpuMesh`]) and a model's leaf storage
//! ([`LeafStore`]). Positions are in model space unless a field says world; colours are linear
//! unless a field says sRGB.

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

/// Globals uniform.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Globals {
    pub(super) view_proj: [[f32; 4]; 4],
    pub(super) sun: [f32; 4],
    pub(super) params: [f32; 4],
}

/// Per-tree transform and debug tint (storage buffer, indexed by [`LeafDraw::tree`]).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct TreeTransform {
    /// Model → world.
    pub model: [[f32; 4]; 4],
    /// Debug colour (rgb) and how much it replaces the material (a).
    pub tint: [f32; 4],
}

/// One leaf as the shader reads it (model space).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuLeaf {
    /// Centre (xyz) and the linear rgba8 colour bit-cast into w.
    pub center: [f32; 4],
    /// Half width along the blade's side.
    pub side: [f32; 4],
    /// Half length along the blade's axis.
    pub axis: [f32; 4],
}

/// One drawn leaf.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct LeafDraw {
    /// Index into the model's leaf buffer.
    pub leaf: u32,
    /// Index into the frame's tree transforms.
    pub tree: u32,
    /// Seed 004 enlargement (1: none).
    pub scale: f32,
    /// Padding.
    pub pad: u32,
}

/// Mesh vertex (model space, linear colour).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct MeshVertex {
    /// Position.
    pub pos: [f32; 3],
    /// Normal.
    pub normal: [f32; 3],
    /// Linear RGBA.
    pub color: [f32; 4],
}

/// One instance of a mesh.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct MeshInstance {
    /// Model → world, columns.
    pub model: [[f32; 4]; 4],
    /// Debug tint.
    pub tint: [f32; 4],
}

/// One billboard quad.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct BillboardInstance {
    /// Quad centre, world.
    pub center: [f32; 3],
    /// Half extent to the right, world.
    pub right: [f32; 3],
    /// Half extent upwards, world.
    pub up: [f32; 3],
    /// Texture array layers of up to three frames.
    pub layers: [u32; 3],
    /// Blend weights (sum 1; unused frames 0).
    pub weights: [f32; 3],
    /// Debug tint.
    pub tint: [f32; 4],
    /// Screen-door coverage of a cross-fade: `c > 0` keeps the pixels whose 4 × 4 ordered-dither
    /// threshold is below `c`, `c < 0` those at or above `1 + c` (the complement of `1 + c`), so
    /// two quads at `w` and `−(1 − w)` cover each pixel exactly once. 1 draws every pixel.
    pub coverage: f32,
}

/// A mesh uploaded once (bark variant, hull level, ground).
#[derive(Debug)]
pub struct GpuMesh {
    pub(super) vertices: wgpu::Buffer,
    pub(super) indices: wgpu::Buffer,
    pub(super) index_count: u32,
}

impl GpuMesh {
    /// Uploads `vertices` and `indices` (triangles).
    pub fn new(device: &wgpu::Device, vertices: &[MeshVertex], indices: &[u32]) -> Self {
        let zero_v = [MeshVertex::zeroed()];
        let zero_i = [0u32; 3];
        let v = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mesh vertices"),
            contents: bytemuck::cast_slice(if vertices.is_empty() { &zero_v } else { vertices }),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let i = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mesh indices"),
            contents: bytemuck::cast_slice(if indices.is_empty() { &zero_i } else { indices }),
            usage: wgpu::BufferUsages::INDEX,
        });
        Self {
            vertices: v,
            indices: i,
            index_count: if indices.is_empty() { 0 } else { indices.len() as u32 },
        }
    }

    /// Triangles.
    pub fn triangles(&self) -> u64 {
        u64::from(self.index_count / 3)
    }
}

/// A model's leaves on the GPU: a storage buffer and its bind group.
#[derive(Debug)]
pub struct LeafStore {
    pub(super) buffer: wgpu::Buffer,
    pub(super) bind_group: wgpu::BindGroup,
    pub(super) capacity: u32,
}

impl LeafStore {
    /// Leaves it holds at most.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Writes `leaves` at index `at` (silently clipped to the capacity).
    pub fn write(&self, queue: &wgpu::Queue, at: u32, leaves: &[GpuLeaf]) {
        if at >= self.capacity || leaves.is_empty() {
            return;
        }
        let n = leaves.len().min((self.capacity - at) as usize);
        queue.write_buffer(
            &self.buffer,
            u64::from(at) * size_of::<GpuLeaf>() as u64,
            bytemuck::cast_slice(&leaves[..n]),
        );
    }
}
