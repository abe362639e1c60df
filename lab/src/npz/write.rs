//! Writing `.npy` bytes exactly as NumPy's `np.save` does.

use super::*;

/// Magic, version, header length and the padded header dict, exactly as NumPy writes them.
pub(super) fn npy_header(descr: &str, shape: &[usize]) -> Vec<u8> {
    let shape_repr = match shape {
        [] => "()".to_owned(),
        [n] => format!("({n},)"),
        _ => format!("({})", shape.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")),
    };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_repr}, }}");
    if let Some(first) = shape.first() {
        // Room for the first axis to grow in place (numpy's GROWTH_AXIS_MAX_DIGITS).
        dict.push_str(&" ".repeat(GROWTH_AXIS_MAX_DIGITS.saturating_sub(first.to_string().len())));
    }
    // NumPy pads `dict + '\n'` with spaces until magic + version + length field + header is a
    // multiple of 64 (a full 64 when it already is); version 1.0 has a 2-byte length field and is
    // used whenever the padded length fits, 2.0 (4 bytes) otherwise.
    let text_len = dict.len() + 1;
    let padded = |prefix: usize| text_len + NPY_ALIGN - (prefix + text_len) % NPY_ALIGN;
    let v1_len = padded(NPY_MAGIC.len() + 2 + 2);
    let mut out = Vec::with_capacity(v1_len + 12);
    out.extend_from_slice(NPY_MAGIC);
    let header_len = match u16::try_from(v1_len) {
        Ok(len) => {
            out.extend_from_slice(&[1, 0]);
            out.extend_from_slice(&len.to_le_bytes());
            v1_len
        }
        Err(_) => {
            let len = padded(NPY_MAGIC.len() + 2 + 4);
            out.extend_from_slice(&[2, 0]);
            out.extend_from_slice(&(len as u32).to_le_bytes());
            len
        }
    };
    out.extend_from_slice(dict.as_bytes());
    out.resize(out.len() + header_len - text_len, b' ');
    out.push(b'\n');
    out
}

pub(super) fn encode_data(data: &NpyData, out: &mut Vec<u8>) {
    macro_rules! le {
        ($v:expr) => {
            $v.iter().for_each(|x| out.extend_from_slice(&x.to_le_bytes()))
        };
    }
    match data {
        NpyData::Bool(v) => out.extend(v.iter().map(|&b| u8::from(b))),
        NpyData::U8(v) => out.extend_from_slice(v),
        NpyData::I8(v) => le!(v),
        NpyData::U16(v) => le!(v),
        NpyData::I16(v) => le!(v),
        NpyData::U32(v) => le!(v),
        NpyData::I32(v) => le!(v),
        NpyData::U64(v) => le!(v),
        NpyData::I64(v) => le!(v),
        NpyData::F32(v) => le!(v),
        NpyData::F64(v) => le!(v),
        NpyData::Str(v) => encode_strings(v, out),
        NpyData::Object(pickle) => out.extend_from_slice(pickle),
    }
}

/// NumPy's `<U n`: each string as `n` UTF-32LE code units, NUL-padded.
pub(super) fn encode_strings(values: &[String], out: &mut Vec<u8>) {
    let width = str_width(values);
    for s in values {
        let mut count = 0;
        for c in s.chars() {
            out.extend_from_slice(&u32::from(c).to_le_bytes());
            count += 1;
        }
        out.resize(out.len() + 4 * (width - count), 0);
    }
}

/// The `n` of `<U n`: the longest string, at least 1 (`np.array("")` is `<U1`).
pub(super) fn str_width(values: &[String]) -> usize {
    values.iter().map(|s| s.chars().count()).max().unwrap_or(0).max(1)
}
