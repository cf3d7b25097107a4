//! Offscreen targets (sRGB colour and depth) and reading the colour back to the CPU: the window
//! shows the colour texture, `--screenshot` reads it back, so both draw the same pixels.

#[cfg(doc)]
use super::supports_ui_view;
use super::{COLOR_FORMAT, DEPTH_FORMAT, GpuError, Renderer};

/// Offscreen colour and depth targets.
#[derive(Debug)]
pub struct Target {
    /// Colour texture ([`COLOR_FORMAT`]).
    pub color: wgpu::Texture,
    /// Its view.
    pub color_view: wgpu::TextureView,
    /// The same texels viewed as plain `Rgba8Unorm`: what egui samples (egui composites in
    /// gamma space, so it must read the sRGB bytes as they are).
    /// `None` for headless targets ([`Target::new`]): the view needs the adapter's
    /// `VIEW_FORMATS` downlevel flag, which GL adapters may lack, and only the window uses it.
    pub ui_view: Option<wgpu::TextureView>,
    pub(super) depth_view: wgpu::TextureView,
    /// Size.
    pub size: (u32, u32),
}

impl Target {
    /// Headless targets of `width × height` (at least 1), without [`Target::ui_view`].
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        Self::build(device, width, height, false)
    }

    /// Targets with [`Target::ui_view`], for a window. The device's adapter must support
    /// [`wgpu::DownlevelFlags::VIEW_FORMATS`] ([`supports_ui_view`]).
    pub fn with_ui_view(device: &wgpu::Device, width: u32, height: u32) -> Self {
        Self::build(device, width, height, true)
    }

    fn build(device: &wgpu::Device, width: u32, height: u32, ui: bool) -> Self {
        let size = wgpu::Extent3d {
            width: width.max(1),
            height: height.max(1),
            depth_or_array_layers: 1,
        };
        let color = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("colour target"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: COLOR_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: if ui { &[wgpu::TextureFormat::Rgba8Unorm] } else { &[] },
        });
        let depth = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("depth target"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        Self {
            color_view: color.create_view(&wgpu::TextureViewDescriptor::default()),
            ui_view: ui.then(|| {
                color.create_view(&wgpu::TextureViewDescriptor {
                    format: Some(wgpu::TextureFormat::Rgba8Unorm),
                    ..wgpu::TextureViewDescriptor::default()
                })
            }),
            depth_view: depth.create_view(&wgpu::TextureViewDescriptor::default()),
            color,
            size: (size.width, size.height),
        }
    }
}

impl Renderer {
    /// Reads `target`'s colour back as tightly packed sRGB RGBA rows.
    pub fn read_back(device: &wgpu::Device, queue: &wgpu::Queue, target: &Target) -> Result<Vec<u8>, GpuError> {
        let (w, h) = target.size;
        let row = 4 * w;
        let padded = row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buf = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read-back"),
            size: u64::from(padded) * u64::from(h),
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("read-back"),
        });
        enc.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &target.color,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &buf,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(h),
                },
            },
            wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
        );
        queue.submit([enc.finish()]);
        let slice = buf.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let data = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let mut out = Vec::with_capacity((row * h) as usize);
        for y in 0..h as usize {
            let s = y * padded as usize;
            out.extend_from_slice(&data[s..s + row as usize]);
        }
        drop(data);
        buf.unmap();
        Ok(out)
    }
}
