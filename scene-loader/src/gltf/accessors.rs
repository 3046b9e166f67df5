//! Accessors decoded by hand: every offset, stride and count is checked against its
//! buffer view, sparse accessors are patched in, and colours and indices are read in the
//! component types the specification allows, so a bad file gives a message, never a panic.

use glam::Vec4;
use gltf::json;
use gltf::json::validation::Checked;

use super::{Loader, MAX_ZERO_FILLED_COMPONENTS};

/// Conversion from a decoded accessor component.
pub(super) trait FromComponent: Copy + Default {
    fn from_component(v: f64) -> Self;
}

impl FromComponent for f32 {
    fn from_component(v: f64) -> Self {
        v as f32
    }
}

impl FromComponent for u32 {
    fn from_component(v: f64) -> Self {
        // Only reached with integer component types, whose values f64 holds exactly.
        v as u32
    }
}

/// One component at the start of `bytes`, normalised to [0,1] / [-1,1] if asked.
pub(super) fn read_component(
    bytes: &[u8],
    ty: json::accessor::ComponentType,
    normalized: bool,
) -> Option<f64> {
    use json::accessor::ComponentType as C;
    fn arr<const N: usize>(b: &[u8]) -> Option<[u8; N]> {
        b.get(..N)?.try_into().ok()
    }
    let norm = |v: f64, max: f64| {
        if normalized { (v / max).max(-1.0) } else { v }
    };
    Some(match ty {
        C::I8 => norm(f64::from(i8::from_le_bytes(arr(bytes)?)), 127.0),
        C::U8 => norm(f64::from(u8::from_le_bytes(arr(bytes)?)), 255.0),
        C::I16 => norm(f64::from(i16::from_le_bytes(arr(bytes)?)), 32767.0),
        C::U16 => norm(f64::from(u16::from_le_bytes(arr(bytes)?)), 65535.0),
        C::U32 => f64::from(u32::from_le_bytes(arr(bytes)?)),
        C::F32 => f64::from(f32::from_le_bytes(arr(bytes)?)),
    })
}

impl Loader<'_> {
    /// The bytes of buffer view `index` and its stride, bounds-checked against its buffer.
    pub(super) fn view_bytes(
        &self,
        index: usize,
    ) -> std::result::Result<(&[u8], Option<usize>), String> {
        let view = self
            .root
            .buffer_views
            .get(index)
            .ok_or_else(|| format!("buffer view {index} does not exist"))?;
        let stride = view.byte_stride.map(|s| s.0).filter(|&s| s > 0);
        if let Some(Some(decoded)) = self.decoded_views.get(index) {
            return Ok((decoded, stride));
        }
        let b = view.buffer.value();
        let buffer = self
            .buffers
            .get(b)
            .ok_or_else(|| format!("buffer view {index} refers to missing buffer {b}"))?;
        let offset = view.byte_offset.map_or(0, |o| o.0);
        let end = offset.checked_add(view.byte_length.0);
        let slice = end
            .and_then(|end| buffer.get(usize::try_from(offset).ok()?..usize::try_from(end).ok()?));
        let slice = slice.ok_or_else(|| {
            format!(
                "buffer view {index} covers bytes {offset}..{} but buffer {b} has only {} bytes",
                end.map_or_else(|| "overflow".to_string(), |e| e.to_string()),
                buffer.len()
            )
        })?;
        Ok((slice, stride))
    }

    /// Decode accessor `index`, which must have `dims` components per element, into a
    /// flat array. Every offset is checked, so a bad file gives a message, never a panic.
    pub(super) fn read_accessor<T: FromComponent>(
        &self,
        index: usize,
        dims: usize,
    ) -> std::result::Result<Vec<T>, String> {
        let acc = self.accessor(index)?;
        let Checked::Valid(json::accessor::GenericComponentType(ty)) = acc.component_type else {
            return Err(format!("accessor {index} has an invalid componentType"));
        };
        let Checked::Valid(kind) = acc.type_ else {
            return Err(format!("accessor {index} has an invalid type"));
        };
        if kind.multiplicity() != dims {
            return Err(format!(
                "accessor {index} has type {kind:?} but {dims} components per element are required"
            ));
        }
        let count = usize::try_from(acc.count.0)
            .map_err(|_| format!("accessor {index}: count {} is too large", acc.count.0))?;
        let comp_size = ty.size();
        let elem_size = comp_size * dims;
        let total = count
            .checked_mul(dims)
            .ok_or_else(|| format!("accessor {index}: count {count} is too large"))?;

        let mut out: Vec<T> = Vec::new();
        match acc.buffer_view {
            Some(view) => {
                let (bytes, stride) = self
                    .view_bytes(view.value())
                    .map_err(|m| format!("accessor {index}: {m}"))?;
                let stride = stride.unwrap_or(elem_size);
                if stride < elem_size {
                    return Err(format!(
                        "accessor {index}: byteStride {stride} is smaller than the element size \
                         {elem_size}"
                    ));
                }
                let offset = usize::try_from(acc.byte_offset.map_or(0, |o| o.0))
                    .map_err(|_| format!("accessor {index}: byteOffset is too large"))?;
                if count > 0 {
                    let end = (count - 1)
                        .checked_mul(stride)
                        .and_then(|x| x.checked_add(offset))
                        .and_then(|x| x.checked_add(elem_size));
                    match end {
                        Some(end) if end <= bytes.len() => {}
                        _ => {
                            return Err(format!(
                                "accessor {index} ({count} elements of {elem_size} bytes, stride \
                                 {stride}, offset {offset}) reads past the end of buffer view {} \
                                 ({} bytes)",
                                view.value(),
                                bytes.len()
                            ));
                        }
                    }
                }
                out.reserve_exact(total);
                for e in 0..count {
                    let at = offset + e * stride;
                    for c in 0..dims {
                        let v = bytes
                            .get(at + c * comp_size..)
                            .and_then(|b| read_component(b, ty, acc.normalized))
                            .ok_or_else(|| {
                                format!("accessor {index}: element {e} is out of range")
                            })?;
                        out.push(T::from_component(v));
                    }
                }
            }
            None => {
                if total > MAX_ZERO_FILLED_COMPONENTS {
                    return Err(format!(
                        "accessor {index} has no buffer view and {count} elements (too many)"
                    ));
                }
                out.resize(total, T::default());
            }
        }
        if let Some(sparse) = &acc.sparse {
            self.apply_sparse(index, sparse, ty, acc.normalized, dims, count, &mut out)?;
        }
        Ok(out)
    }

    #[allow(clippy::too_many_arguments)] // all describe the one accessor being patched
    pub(super) fn apply_sparse<T: FromComponent>(
        &self,
        index: usize,
        sparse: &json::accessor::sparse::Sparse,
        ty: json::accessor::ComponentType,
        normalized: bool,
        dims: usize,
        count: usize,
        out: &mut [T],
    ) -> std::result::Result<(), String> {
        let n = usize::try_from(sparse.count.0)
            .map_err(|_| format!("accessor {index}: sparse count is too large"))?;
        let Checked::Valid(json::accessor::IndexComponentType(ity)) = sparse.indices.component_type
        else {
            return Err(format!(
                "accessor {index}: sparse indices have an invalid componentType"
            ));
        };
        let isize_ = ity.size();
        let elem_size = ty.size() * dims;
        let region = |view: usize, offset: u64, elem: usize, what: &str| {
            let (bytes, _) = self
                .view_bytes(view)
                .map_err(|m| format!("accessor {index}: sparse {what}: {m}"))?;
            let offset = usize::try_from(offset).ok();
            let end = offset.and_then(|o| n.checked_mul(elem)?.checked_add(o));
            match (offset, end) {
                (Some(o), Some(e)) if e <= bytes.len() => Ok(bytes.get(o..e).unwrap_or_default()),
                _ => Err(format!(
                    "accessor {index}: sparse {what} ({n} x {elem} bytes) read past the end of \
                     buffer view {view} ({} bytes)",
                    bytes.len()
                )),
            }
        };
        let ibytes = region(
            sparse.indices.buffer_view.value(),
            sparse.indices.byte_offset.0,
            isize_,
            "indices",
        )?;
        let vbytes = region(
            sparse.values.buffer_view.value(),
            sparse.values.byte_offset.0,
            elem_size,
            "values",
        )?;
        for k in 0..n {
            let target = ibytes
                .get(k * isize_..)
                .and_then(|b| read_component(b, ity, false))
                .ok_or_else(|| format!("accessor {index}: sparse index {k} is out of range"))?;
            let target = target as usize;
            if target >= count {
                return Err(format!(
                    "accessor {index}: sparse index {k} targets element {target} but the accessor \
                     has {count}"
                ));
            }
            for c in 0..dims {
                let v = vbytes
                    .get(k * elem_size + c * ty.size()..)
                    .and_then(|b| read_component(b, ty, normalized))
                    .ok_or_else(|| format!("accessor {index}: sparse value {k} is out of range"))?;
                if let Some(slot) = out.get_mut(target * dims + c) {
                    *slot = T::from_component(v);
                }
            }
        }
        Ok(())
    }

    /// Accessor `index`, or a message saying it does not exist.
    pub(super) fn accessor(&self, index: usize) -> std::result::Result<&json::Accessor, String> {
        self.root
            .accessors
            .get(index)
            .ok_or_else(|| format!("accessor {index} does not exist"))
    }

    /// Read a `COLOR_0` accessor: VEC3 (alpha 1) or VEC4, float or normalized unsigned
    /// 8/16-bit, as the glTF specification allows.
    pub(super) fn read_colors(&self, index: usize) -> std::result::Result<Vec<Vec4>, String> {
        use json::accessor::ComponentType as C;
        let acc = self.accessor(index)?;
        let dims = match acc.type_ {
            Checked::Valid(json::accessor::Type::Vec3) => 3,
            Checked::Valid(json::accessor::Type::Vec4) => 4,
            _ => return Err(format!("accessor {index} must be VEC3 or VEC4")),
        };
        match acc.component_type {
            Checked::Valid(json::accessor::GenericComponentType(C::F32)) => {}
            Checked::Valid(json::accessor::GenericComponentType(C::U8 | C::U16))
                if acc.normalized => {}
            _ => {
                return Err(format!(
                    "accessor {index} must hold floats or normalized unsigned 8 or 16-bit \
                     integers"
                ));
            }
        }
        let values = self.read_accessor::<f32>(index, dims)?;
        Ok(values
            .chunks_exact(dims)
            .map(|c| match c {
                [r, g, b] => Vec4::new(*r, *g, *b, 1.0),
                _ => Vec4::from_slice(c),
            })
            .collect())
    }

    /// Read an index accessor (unsigned 8, 16 or 32-bit scalars).
    pub(super) fn read_indices(&self, index: usize) -> std::result::Result<Vec<u32>, String> {
        use json::accessor::ComponentType as C;
        let acc = self.accessor(index)?;
        match acc.component_type {
            Checked::Valid(json::accessor::GenericComponentType(C::U8 | C::U16 | C::U32)) => {}
            _ => {
                return Err(format!(
                    "accessor {index} must hold unsigned 8, 16 or 32-bit integers to be used as \
                     indices"
                ));
            }
        }
        self.read_accessor::<u32>(index, 1)
    }
}
