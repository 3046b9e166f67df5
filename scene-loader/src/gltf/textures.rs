//! Textures: each glTF texture with its sampler, over images decoded once to RGBA8 even
//! when several textures share them.

use std::borrow::Cow;

use dray_core::texture::{Filter, Sampler, Texture, Wrap};
use gltf::json;
use gltf::json::validation::Checked;

use super::Loader;
use super::buffers::{display_uri, read_uri};
use crate::error::Result;

/// An image decoded to RGBA8, shared by the textures that use it.
#[derive(Clone)]
pub(super) struct DecodedImage {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) texels: std::sync::Arc<[[u8; 4]]>,
}

impl Loader<'_> {
    /// One [`Texture`] per glTF texture, in order, so a material's texture index can be
    /// used as is. Each image is decoded once even when several textures share it.
    pub(super) fn load_textures(&mut self) -> Result<()> {
        let mut images: Vec<Option<DecodedImage>> = vec![None; self.root.images.len()];
        let mut textures = Vec::with_capacity(self.root.textures.len());
        for (t, texture) in self.root.textures.iter().enumerate() {
            let image_index = texture.source.value();
            let slot = images.get_mut(image_index).ok_or_else(|| {
                self.error(format!(
                    "texture {t} refers to image {image_index}, which does not exist"
                ))
            })?;
            if slot.is_none() {
                *slot = Some(self.decode_image(image_index)?);
            }
            let Some(DecodedImage {
                width,
                height,
                texels,
            }) = slot.clone()
            else {
                return Err(self.error(format!("texture {t}: image {image_index} was not decoded")));
            };
            let image = self.root.images.get(image_index);
            let name = texture
                .name
                .clone()
                .or_else(|| image.and_then(|i| i.name.clone()))
                .or_else(|| {
                    image
                        .and_then(|i| i.uri.as_deref())
                        .filter(|u| !u.starts_with("data:"))
                        .map(str::to_string)
                })
                .unwrap_or_else(|| format!("texture #{t}"));
            let sampler = texture
                .sampler
                .and_then(|s| self.root.samplers.get(s.value()))
                .map(convert_sampler)
                .unwrap_or_default();
            textures.push(Texture {
                name,
                width,
                height,
                texels,
                sampler,
            });
        }
        self.scene.textures = textures;
        Ok(())
    }

    pub(super) fn decode_image(&self, index: usize) -> Result<DecodedImage> {
        crate::cancel::check()?;
        let image = self
            .root
            .images
            .get(index)
            .ok_or_else(|| self.error(format!("image {index} does not exist")))?;
        let (what, bytes): (String, Cow<'_, [u8]>) = match (&image.uri, image.buffer_view) {
            (Some(uri), _) => {
                let what = format!("image {index} ({})", display_uri(uri));
                let bytes = read_uri(self.path, uri, None)
                    .map_err(|m| self.error(format!("{what}: {m}")))?;
                (what, Cow::Owned(bytes))
            }
            (None, Some(view)) => {
                let what = format!("image {index} (buffer view {})", view.value());
                let (bytes, _) = self
                    .view_bytes(view.value())
                    .map_err(|m| self.error(format!("{what}: {m}")))?;
                (what, Cow::Borrowed(bytes))
            }
            (None, None) => {
                return Err(self.error(format!("image {index} has neither a uri nor a bufferView")));
            }
        };
        let decoded = image::load_from_memory(&bytes)
            .map_err(|e| self.error(format!("{what}: cannot decode image: {e}")))?
            .into_rgba8();
        let (width, height) = decoded.dimensions();
        let texels = decoded
            .into_raw()
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect();
        Ok(DecodedImage {
            width,
            height,
            texels,
        })
    }
}

fn convert_sampler(s: &json::texture::Sampler) -> Sampler {
    use json::texture::{MagFilter, WrappingMode};
    let wrap = |w: Checked<WrappingMode>| match w {
        Checked::Valid(WrappingMode::ClampToEdge) => Wrap::ClampToEdge,
        Checked::Valid(WrappingMode::MirroredRepeat) => Wrap::MirroredRepeat,
        _ => Wrap::Repeat,
    };
    Sampler {
        wrap_s: wrap(s.wrap_s),
        wrap_t: wrap(s.wrap_t),
        filter: match s.mag_filter {
            Some(Checked::Valid(MagFilter::Nearest)) => Filter::Nearest,
            _ => Filter::Linear,
        },
    }
}
