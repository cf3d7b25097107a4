//! One frame: the camera and lighting ([`FrameCamera`]), what is drawn ([`FrameDraws`]), the
//! instance buffers uploaded once per generation, and the render pass (meshes, then leaves,
//! then billboards) into a [`Target`]. The view-projection maps to depth 0..1.

use glam::{Mat4, Vec3};
use wgpu::util::DeviceExt;

use super::buffers::{BillboardInstance, Globals, GpuMesh, LeafDraw, LeafStore, MeshInstance, TreeTransform};
use super::{BILLBOARD_ALPHA_CUTOFF, LEAF_ALPHA_CUTOFF, LEAF_DRAWS_PER_BUFFER, Renderer, Target, srgb_to_linear};

/// What one frame draws, ready for [`Renderer::render`].
#[derive(Debug, Default)]
pub struct FrameDraws<'a> {
    /// Identifies the instance data: [`Renderer::render`] uploads it once per generation and
    /// redraws it from any camera until the generation changes (0: always upload).
    pub generation: u64,
    /// Tree transforms (indexed by leaf draws).
    pub trees: &'a [TreeTransform],
    /// Leaf draws per model leaf store.
    pub leaves: Vec<(&'a LeafStore, &'a [LeafDraw])>,
    /// Mesh instances per mesh.
    pub meshes: Vec<(&'a GpuMesh, &'a [MeshInstance])>,
    /// Billboard quads.
    pub billboards: &'a [BillboardInstance],
}

/// Instance buffers of one generation.
#[derive(Debug)]
pub(super) struct Uploaded {
    generation: u64,
    leaves: Vec<(wgpu::BindGroup, wgpu::Buffer, u32)>,
    meshes: Vec<(wgpu::Buffer, wgpu::Buffer, u32, wgpu::Buffer, u32)>,
    billboards: Option<(wgpu::Buffer, u32)>,
}

/// Camera and lighting of a frame.
#[derive(Debug, Clone, Copy)]
pub struct FrameCamera {
    /// View-projection (depth 0..1).
    pub view_proj: Mat4,
    /// Direction towards the sun.
    pub sun_direction: Vec3,
    /// Sun intensity.
    pub sun: f32,
    /// Ambient intensity.
    pub ambient: f32,
    /// Clear colour (sRGB bytes).
    pub clear: [u8; 3],
}

impl Renderer {
    /// Renders `draws` into `target`.
    pub fn render(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        target: &Target,
        cam: &FrameCamera,
        draws: &FrameDraws<'_>,
    ) {
        let g = Globals {
            view_proj: cam.view_proj.to_cols_array_2d(),
            sun: {
                let d = cam.sun_direction.normalize_or_zero();
                [d.x, d.y, d.z, cam.sun]
            },
            params: [cam.ambient, LEAF_ALPHA_CUTOFF, BILLBOARD_ALPHA_CUTOFF, 0.0],
        };
        queue.write_buffer(&self.globals, 0, bytemuck::bytes_of(&g));
        let need = draws.trees.len().max(1) as u64;
        if need > self.trees_capacity {
            self.trees_capacity = need.next_power_of_two();
            self.trees = Self::trees_buffer(device, self.trees_capacity);
            self.global_group = Self::global_group(
                device,
                &self.global_layout,
                &self.globals,
                &self.trees,
                &self.leaf_mask_view,
                &self.nearest,
                &self.billboard_view,
                &self.linear,
            );
        }
        let fresh = draws.generation == 0 || self.uploaded.as_ref().is_none_or(|u| u.generation != draws.generation);
        if fresh {
            if !draws.trees.is_empty() {
                queue.write_buffer(&self.trees, 0, bytemuck::cast_slice(draws.trees));
            }
            let init = |label: &str, contents: &[u8]| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::VERTEX,
                })
            };
            self.uploaded = Some(Uploaded {
                generation: draws.generation,
                leaves: draws
                    .leaves
                    .iter()
                    .flat_map(|(store, d)| d.chunks(LEAF_DRAWS_PER_BUFFER).map(move |c| (store, c)))
                    .filter(|(_, c)| !c.is_empty())
                    .map(|(store, c)| {
                        (
                            store.bind_group.clone(),
                            init("leaf draws", bytemuck::cast_slice(c)),
                            c.len() as u32,
                        )
                    })
                    .collect(),
                meshes: draws
                    .meshes
                    .iter()
                    .filter(|(m, i)| !i.is_empty() && m.index_count > 0)
                    .map(|(m, i)| {
                        (
                            m.vertices.clone(),
                            m.indices.clone(),
                            m.index_count,
                            init("mesh instances", bytemuck::cast_slice(i)),
                            i.len() as u32,
                        )
                    })
                    .collect(),
                billboards: (!draws.billboards.is_empty()).then(|| {
                    (
                        init("billboards", bytemuck::cast_slice(draws.billboards)),
                        draws.billboards.len() as u32,
                    )
                }),
            });
        }
        let Some(up) = &self.uploaded else { return };
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        {
            let [r, gr, b] = cam.clear.map(|c| srgb_to_linear(c) as f64);
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("scene"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &target.color_view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color { r, g: gr, b, a: 1.0 }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &target.depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: wgpu::StoreOp::Discard,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_bind_group(0, &self.global_group, &[]);
            // Group 1 must be bound for every pipeline; meshes and billboards do not read it.
            pass.set_bind_group(1, &self.dummy_leaves.bind_group, &[]);
            pass.set_pipeline(&self.mesh_pipeline);
            for (v, i, count, inst, n) in &up.meshes {
                pass.set_vertex_buffer(0, v.slice(..));
                pass.set_vertex_buffer(1, inst.slice(..));
                pass.set_index_buffer(i.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..*count, 0, 0..*n);
            }
            pass.set_pipeline(&self.leaf_pipeline);
            for (group, buf, n) in &up.leaves {
                pass.set_bind_group(1, group, &[]);
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw(0..6, 0..*n);
            }
            if let Some((buf, n)) = &up.billboards {
                pass.set_pipeline(&self.billboard_pipeline);
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw(0..6, 0..*n);
            }
        }
        queue.submit([enc.finish()]);
    }
}
