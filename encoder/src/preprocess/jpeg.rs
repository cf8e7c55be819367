//! Baseline JPEG decoding bit-identical to libjpeg-turbo's defaults (what Pillow and therefore the
//! segment_anything / open_clip references use): `JDCT_ISLOW` integer IDCT (`jidctint.c`), fancy
//! (triangle) chroma upsampling (`jdsample.c`, `h2v2_fancy_upsample`) and the fixed-point
//! YCbCr→RGB tables of `jdcolor.c`.
//!
//! Scope: baseline / extended sequential Huffman (SOF0/SOF1), 8-bit, one scan, 1 (grey) or 3
//! (YCbCr) components, chroma either full size or 2x2-subsampled (4:2:0), restart intervals.
//! [`decode`] returns `Ok(None)` for anything else; the caller then falls back to the `image`
//! crate (whose decoder differs from libjpeg-turbo by a few levels on some pixels).

use image::RgbImage;

/// Why a stream could not be decoded (the caller reports it with the file path).
pub(crate) type DecodeError = String;

const ZIGZAG: [usize; 64] = [
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5, 12, 19, 26, 33, 40, 48, 41, 34, 27, 20,
    13, 6, 7, 14, 21, 28, 35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51, 58, 59,
    52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
];

#[derive(Clone, Default)]
struct Huffman {
    /// (code length, code, symbol) lookup per length: maxcode/valptr/mincode as in JPEG F.2.2.3.
    maxcode: [i32; 18],
    valptr: [i32; 17],
    mincode: [i32; 17],
    values: Vec<u8>,
}

impl Huffman {
    fn new(counts: &[u8; 16], values: Vec<u8>) -> Self {
        let mut h = Huffman {
            values,
            ..Default::default()
        };
        let (mut code, mut k) = (0i32, 0i32);
        for l in 1..=16 {
            let n = i32::from(counts[l - 1]);
            if n == 0 {
                h.maxcode[l] = -1;
            } else {
                h.valptr[l] = k;
                h.mincode[l] = code;
                code += n;
                k += n;
                h.maxcode[l] = code - 1;
            }
            code <<= 1;
        }
        h.maxcode[17] = i32::MAX;
        h
    }
}

struct Bits<'a> {
    data: &'a [u8],
    pos: usize,
    acc: u64,
    n: u32,
    hit_marker: bool,
}

impl<'a> Bits<'a> {
    fn fill(&mut self) {
        while self.n <= 56 {
            let mut byte = 0u8;
            if !self.hit_marker && self.pos < self.data.len() {
                let b = self.data[self.pos];
                if b == 0xFF {
                    let next = self.data.get(self.pos + 1).copied().unwrap_or(0xD9);
                    if next == 0x00 {
                        self.pos += 2;
                        byte = 0xFF;
                    } else {
                        // A marker: libjpeg feeds zeros from here on.
                        self.hit_marker = true;
                    }
                } else {
                    self.pos += 1;
                    byte = b;
                }
            }
            self.acc |= u64::from(byte) << (56 - self.n);
            self.n += 8;
        }
    }

    fn bit(&mut self) -> i32 {
        if self.n == 0 {
            self.fill();
        }
        let b = (self.acc >> 63) as i32;
        self.acc <<= 1;
        self.n -= 1;
        b
    }

    fn bits(&mut self, count: u32) -> i32 {
        if count == 0 {
            return 0;
        }
        if self.n < count {
            self.fill();
        }
        let v = (self.acc >> (64 - count)) as i32;
        self.acc <<= count;
        self.n -= count;
        v
    }

    fn decode(&mut self, h: &Huffman) -> Result<u8, DecodeError> {
        let mut code = self.bit();
        let mut l = 1;
        while l <= 16 && code > h.maxcode[l] {
            code = (code << 1) | self.bit();
            l += 1;
        }
        if l > 16 {
            return Err("corrupt Huffman code".into());
        }
        let idx = (h.valptr[l] + code - h.mincode[l]) as usize;
        h.values
            .get(idx)
            .copied()
            .ok_or_else(|| "corrupt Huffman table".to_string())
    }

    /// Skips to the byte after the next RSTn marker.
    fn restart(&mut self) {
        self.acc = 0;
        self.n = 0;
        self.hit_marker = false;
        while self.pos + 1 < self.data.len() {
            if self.data[self.pos] == 0xFF && (0xD0..=0xD7).contains(&self.data[self.pos + 1]) {
                self.pos += 2;
                return;
            }
            self.pos += 1;
        }
    }
}

fn extend(v: i32, s: u32) -> i32 {
    if s == 0 {
        0
    } else if v < (1 << (s - 1)) {
        v - (1 << s) + 1
    } else {
        v
    }
}

// jidctint.c constants (CONST_BITS = 13).
const CONST_BITS: i32 = 13;
const PASS1_BITS: i32 = 2;
const FIX_0_298631336: i64 = 2446;
const FIX_0_390180644: i64 = 3196;
const FIX_0_541196100: i64 = 4433;
const FIX_0_765366865: i64 = 6270;
const FIX_0_899976223: i64 = 7373;
const FIX_1_175875602: i64 = 9633;
const FIX_1_501321110: i64 = 12299;
const FIX_1_847759065: i64 = 15137;
const FIX_1_961570560: i64 = 16069;
const FIX_2_053119869: i64 = 16819;
const FIX_2_562915447: i64 = 20995;
const FIX_3_072711026: i64 = 25172;

#[inline]
fn descale(x: i64, n: i32) -> i64 {
    (x + (1 << (n - 1))) >> n
}

/// libjpeg's post-IDCT range limit: `x + 128` clamped to 0..=255 for `x` in -512..512, wrapping
/// (mod 1024) beyond, exactly as `IDCT_range_limit[x & RANGE_MASK]`.
#[inline]
fn idct_limit(x: i64) -> u8 {
    let k = (x & 1023) as i32;
    if k < 128 {
        (k + 128) as u8
    } else if k < 512 {
        255
    } else if k < 896 {
        0
    } else {
        (k - 896) as u8
    }
}

/// One 1-D islow butterfly: returns the 8 outputs before descaling, in order 0..7.
#[inline]
fn idct_1d(v: [i64; 8]) -> [i64; 8] {
    // Even part.
    let (z2, z3) = (v[2], v[6]);
    let z1 = (z2 + z3) * FIX_0_541196100;
    let tmp2 = z1 + z3 * -FIX_1_847759065;
    let tmp3 = z1 + z2 * FIX_0_765366865;
    let tmp0 = (v[0] + v[4]) << CONST_BITS;
    let tmp1 = (v[0] - v[4]) << CONST_BITS;
    let (tmp10, tmp13, tmp11, tmp12) = (tmp0 + tmp3, tmp0 - tmp3, tmp1 + tmp2, tmp1 - tmp2);
    // Odd part.
    let (t0, t1, t2, t3) = (v[7], v[5], v[3], v[1]);
    let (z1, z2, z3, z4) = (t0 + t3, t1 + t2, t0 + t2, t1 + t3);
    let z5 = (z3 + z4) * FIX_1_175875602;
    let (t0, t1, t2, t3) = (
        t0 * FIX_0_298631336,
        t1 * FIX_2_053119869,
        t2 * FIX_3_072711026,
        t3 * FIX_1_501321110,
    );
    let (z1, z2) = (z1 * -FIX_0_899976223, z2 * -FIX_2_562915447);
    let z3 = z3 * -FIX_1_961570560 + z5;
    let z4 = z4 * -FIX_0_390180644 + z5;
    let (t0, t1, t2, t3) = (t0 + z1 + z3, t1 + z2 + z4, t2 + z2 + z3, t3 + z1 + z4);
    [
        tmp10 + t3,
        tmp11 + t2,
        tmp12 + t1,
        tmp13 + t0,
        tmp13 - t0,
        tmp12 - t1,
        tmp11 - t2,
        tmp10 - t3,
    ]
}

/// `jpeg_idct_islow`: dequantised coefficients (natural order) → 8x8 samples.
fn idct_islow(coef: &[i32; 64], q: &[u16; 64], out: &mut [u8], stride: usize) {
    let mut ws = [0i64; 64];
    for c in 0..8 {
        let v: [i64; 8] =
            std::array::from_fn(|r| i64::from(coef[r * 8 + c]) * i64::from(q[r * 8 + c]));
        if v[1..].iter().all(|&x| x == 0) {
            for r in 0..8 {
                ws[r * 8 + c] = v[0] << PASS1_BITS;
            }
            continue;
        }
        let o = idct_1d(v);
        for r in 0..8 {
            ws[r * 8 + c] = descale(o[r], CONST_BITS - PASS1_BITS);
        }
    }
    for r in 0..8 {
        let row: [i64; 8] = std::array::from_fn(|c| ws[r * 8 + c]);
        let dst = &mut out[r * stride..r * stride + 8];
        if row[1..].iter().all(|&x| x == 0) {
            dst.fill(idct_limit(descale(row[0], PASS1_BITS + 3)));
            continue;
        }
        let o = idct_1d(row);
        for c in 0..8 {
            dst[c] = idct_limit(descale(o[c], CONST_BITS + PASS1_BITS + 3));
        }
    }
}

struct Component {
    id: u8,
    h: usize,
    v: usize,
    tq: usize,
    td: usize,
    ta: usize,
}

fn u16be(d: &[u8], i: usize) -> Result<usize, DecodeError> {
    d.get(i..i + 2)
        .map(|s| usize::from(u16::from_be_bytes([s[0], s[1]])))
        .ok_or_else(|| "truncated JPEG header".to_string())
}

/// What the segments before the scan declare: tables, frame size and components.
struct Frame {
    /// Quantisation tables, natural order.
    qt: [[u16; 64]; 4],
    /// DC Huffman tables.
    dc: Vec<Huffman>,
    /// AC Huffman tables.
    ac: Vec<Huffman>,
    comps: Vec<Component>,
    width: usize,
    height: usize,
    /// MCUs between restart markers (0: none).
    restart_interval: usize,
}

impl Frame {
    fn new() -> Frame {
        Frame {
            qt: [[0u16; 64]; 4],
            dc: vec![Huffman::default(); 4],
            ac: vec![Huffman::default(); 4],
            comps: Vec::new(),
            width: 0,
            height: 0,
            restart_interval: 0,
        }
    }

    /// A DQT segment: one or more quantisation tables (8- or 16-bit values).
    fn read_dqt(&mut self, seg: &[u8]) -> Result<(), DecodeError> {
        let mut p = 0;
        while p < seg.len() {
            let (pq, tq) = (seg[p] >> 4, usize::from(seg[p] & 15));
            if tq > 3 {
                return Err("bad quantisation table id".into());
            }
            p += 1;
            for k in 0..64 {
                let v = if pq == 0 {
                    u16::from(*seg.get(p + k).ok_or("truncated DQT")?)
                } else {
                    u16be(seg, p + 2 * k)? as u16
                };
                self.qt[tq][ZIGZAG[k]] = v;
            }
            p += if pq == 0 { 64 } else { 128 };
        }
        Ok(())
    }

    /// A DHT segment: one or more Huffman tables.
    fn read_dht(&mut self, seg: &[u8]) -> Result<(), DecodeError> {
        let mut p = 0;
        while p < seg.len() {
            let (tc, th) = (seg[p] >> 4, usize::from(seg[p] & 15));
            let counts: [u8; 16] = seg
                .get(p + 1..p + 17)
                .ok_or("truncated DHT")?
                .try_into()
                .map_err(|_| "DHT")?;
            let n: usize = counts.iter().map(|&c| usize::from(c)).sum();
            let values = seg.get(p + 17..p + 17 + n).ok_or("truncated DHT")?.to_vec();
            if th > 3 {
                return Err("bad Huffman table id".into());
            }
            let h = Huffman::new(&counts, values);
            if tc == 0 {
                self.dc[th] = h
            } else {
                self.ac[th] = h
            }
            p += 17 + n;
        }
        Ok(())
    }

    /// A baseline or extended sequential SOF segment; `Ok(false)` for a precision other than 8
    /// bits (outside this decoder's scope).
    fn read_sof(&mut self, seg: &[u8]) -> Result<bool, DecodeError> {
        if seg.len() < 6 || seg[0] != 8 {
            return Ok(false);
        }
        self.height = u16be(seg, 1)?;
        self.width = u16be(seg, 3)?;
        let n = usize::from(seg[5]);
        for k in 0..n {
            let c = seg.get(6 + 3 * k..9 + 3 * k).ok_or("truncated SOF")?;
            self.comps.push(Component {
                id: c[0],
                h: usize::from(c[1] >> 4),
                v: usize::from(c[1] & 15),
                tq: usize::from(c[2] & 3),
                td: 0,
                ta: 0,
            });
        }
        Ok(true)
    }

    /// The SOS segment: each component's Huffman tables; `Ok(false)` when the scan does not
    /// hold every component (several scans: outside this decoder's scope).
    fn read_sos(&mut self, seg: &[u8]) -> Result<bool, DecodeError> {
        let ns = usize::from(*seg.first().ok_or("truncated SOS")?);
        if self.comps.is_empty() || ns != self.comps.len() {
            return Ok(false);
        }
        for k in 0..ns {
            let (cid, t) = (seg[1 + 2 * k], seg[2 + 2 * k]);
            let c = self
                .comps
                .iter_mut()
                .find(|c| c.id == cid)
                .ok_or("unknown scan component")?;
            c.td = usize::from(t >> 4) & 3;
            c.ta = usize::from(t & 15) & 3;
        }
        Ok(true)
    }
}

/// Decodes a JPEG stream. `Ok(None)`: a valid JPEG outside this decoder's scope (progressive,
/// CMYK, 12-bit, unusual subsampling, several scans); `Err`: a corrupt stream.
pub(crate) fn decode(data: &[u8]) -> Result<Option<RgbImage>, DecodeError> {
    if data.len() < 4 || data[0] != 0xFF || data[1] != 0xD8 {
        return Err("not a JPEG stream".into());
    }
    let mut frame = Frame::new();
    let mut i = 2;
    loop {
        while i < data.len() && data[i] != 0xFF {
            i += 1;
        }
        while i < data.len() && data[i] == 0xFF {
            i += 1;
        }
        let Some(&marker) = data.get(i) else {
            return Err("no scan in JPEG stream".into());
        };
        i += 1;
        if marker == 0xD8 || (0xD0..=0xD7).contains(&marker) || marker == 0x01 {
            continue;
        }
        if marker == 0xD9 {
            return Err("no scan in JPEG stream".into());
        }
        let len = u16be(data, i)?;
        let seg = data.get(i + 2..i + len).ok_or("truncated JPEG segment")?;
        match marker {
            0xDB => frame.read_dqt(seg)?,
            0xC4 => frame.read_dht(seg)?,
            0xDD => frame.restart_interval = u16be(seg, 0)?,
            0xC0 | 0xC1 => {
                if !frame.read_sof(seg)? {
                    return Ok(None);
                }
            }
            0xC2 | 0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF => return Ok(None),
            0xDA => {
                if !frame.read_sos(seg)? {
                    return Ok(None);
                }
                return decode_scan(&data[i + len..], &frame);
            }
            _ => {}
        }
        i += len;
    }
}

/// The MCU's size in blocks of the largest sampling factors, `(hmax, vmax)`: `(1, 1)` for one
/// (non-interleaved) component; `None` for a layout outside this decoder's scope (other than
/// greyscale or 3 components at 4:4:4 or 4:2:0).
fn mcu_blocks(comps: &[Component]) -> Option<(usize, usize)> {
    let hmax = comps.iter().map(|c| c.h).max().unwrap_or(1);
    let vmax = comps.iter().map(|c| c.v).max().unwrap_or(1);
    let supported = match comps.len() {
        1 => true,
        3 => {
            comps[0].h == hmax
                && comps[0].v == vmax
                && comps[1..].iter().all(|c| c.h == 1 && c.v == 1)
                && ((hmax, vmax) == (1, 1) || (hmax, vmax) == (2, 2))
        }
        _ => false,
    };
    if !supported || comps.iter().any(|c| c.h == 0 || c.v == 0) {
        return None;
    }
    // A single-component scan is non-interleaved: MCU = one block.
    Some(if comps.len() == 1 {
        (1, 1)
    } else {
        (hmax, vmax)
    })
}

/// Decodes one block's coefficients (natural order) into `coef`, the DC as a difference from
/// the component's `pred`, which it updates.
#[inline]
fn decode_block(
    bits: &mut Bits<'_>,
    dc: &Huffman,
    ac: &Huffman,
    pred: &mut i32,
    coef: &mut [i32; 64],
) -> Result<(), DecodeError> {
    coef.fill(0);
    let s = u32::from(bits.decode(dc)?);
    if s > 16 {
        return Err("corrupt DC coefficient".into());
    }
    *pred += extend(bits.bits(s), s);
    coef[0] = *pred;
    let mut k = 1;
    while k < 64 {
        let rs = bits.decode(ac)?;
        let (r, s) = (usize::from(rs >> 4), u32::from(rs & 15));
        if s == 0 {
            if r == 15 {
                k += 16;
                continue;
            }
            break;
        }
        k += r;
        if k > 63 {
            return Err("corrupt AC coefficients".into());
        }
        coef[ZIGZAG[k]] = extend(bits.bits(s), s);
        k += 1;
    }
    Ok(())
}

/// A component's sample plane, padded to whole MCUs: `(row stride, rows, samples)`.
type Plane = (usize, usize, Vec<u8>);

fn decode_scan(data: &[u8], frame: &Frame) -> Result<Option<RgbImage>, DecodeError> {
    let (width, height, comps) = (frame.width, frame.height, &frame.comps[..]);
    if width == 0 || height == 0 {
        return Err("JPEG with zero size".into());
    }
    let Some((hmax, vmax)) = mcu_blocks(comps) else {
        return Ok(None);
    };
    let mcux = width.div_ceil(8 * hmax);
    let mcuy = height.div_ceil(8 * vmax);
    let blocks = |c: &Component| if comps.len() == 1 { (1, 1) } else { (c.h, c.v) };
    let mut planes: Vec<Plane> = comps
        .iter()
        .map(|c| {
            let (ch, cv) = blocks(c);
            let (pw, ph) = (mcux * ch * 8, mcuy * cv * 8);
            (pw, ph, vec![0u8; pw * ph])
        })
        .collect();
    let mut bits = Bits {
        data,
        pos: 0,
        acc: 0,
        n: 0,
        hit_marker: false,
    };
    let mut pred = vec![0i32; comps.len()];
    let mut coef = [0i32; 64];
    let restart_interval = frame.restart_interval;
    for m in 0..mcux * mcuy {
        if restart_interval > 0 && m > 0 && m % restart_interval == 0 {
            bits.restart();
            pred.iter_mut().for_each(|p| *p = 0);
        }
        let (mx, my) = (m % mcux, m / mcux);
        for (ci, c) in comps.iter().enumerate() {
            let (ch, cv) = blocks(c);
            for by in 0..cv {
                for bx in 0..ch {
                    let (dc, ac) = (&frame.dc[c.td], &frame.ac[c.ta]);
                    decode_block(&mut bits, dc, ac, &mut pred[ci], &mut coef)?;
                    let (pw, _, plane) = &mut planes[ci];
                    let x0 = (mx * ch + bx) * 8;
                    let y0 = (my * cv + by) * 8;
                    idct_islow(&coef, &frame.qt[c.tq], &mut plane[y0 * *pw + x0..], *pw);
                }
            }
        }
    }
    let out = planes_to_rgb(&planes, (hmax, vmax), width, height);
    RgbImage::from_raw(width as u32, height as u32, out)
        .map(Some)
        .ok_or_else(|| "size".into())
}

/// Interleaved RGB of the decoded planes: grey for one plane, else Y'CbCr with the chroma
/// upsampled (4:2:0, `mcu == (2, 2)`) or cropped (4:4:4).
fn planes_to_rgb(planes: &[Plane], mcu: (usize, usize), width: usize, height: usize) -> Vec<u8> {
    let mut out = vec![0u8; width * height * 3];
    if planes.len() == 1 {
        let (pw, _, p) = &planes[0];
        for y in 0..height {
            for x in 0..width {
                let v = p[y * pw + x];
                out[(y * width + x) * 3..(y * width + x) * 3 + 3].fill(v);
            }
        }
    } else {
        let (cb, cr) = if mcu == (2, 2) {
            let (cw, chh) = (width.div_ceil(2), height.div_ceil(2));
            (
                h2v2_fancy(&planes[1].2, planes[1].0, cw, chh, width, height),
                h2v2_fancy(&planes[2].2, planes[2].0, cw, chh, width, height),
            )
        } else {
            let crop = |(pw, _, p): &Plane| -> Vec<u8> {
                (0..height)
                    .flat_map(|y| p[y * pw..y * pw + width].iter().copied())
                    .collect()
            };
            (crop(&planes[1]), crop(&planes[2]))
        };
        let (pw, _, yp) = &planes[0];
        ycc_to_rgb(yp, *pw, &cb, &cr, width, height, &mut out);
    }
    out
}

/// libjpeg-turbo `h2v2_fancy_upsample` of a `cw` x `ch` chroma plane (row stride `stride`) to
/// `width` x `height`; context rows beyond the edges duplicate the first/last real row.
fn h2v2_fancy(
    p: &[u8],
    stride: usize,
    cw: usize,
    ch: usize,
    width: usize,
    height: usize,
) -> Vec<u8> {
    let mut out = vec![0u8; width * height];
    let mut row = vec![0u8; cw * 2];
    for iy in 0..ch {
        for v in 0..2 {
            let oy = iy * 2 + v;
            if oy >= height {
                break;
            }
            let near = &p[iy * stride..iy * stride + cw];
            let fy = if v == 0 {
                iy.saturating_sub(1)
            } else {
                (iy + 1).min(ch - 1)
            };
            let far = &p[fy * stride..fy * stride + cw];
            let colsum = |x: usize| i32::from(near[x]) * 3 + i32::from(far[x]);
            if cw == 1 {
                let t = colsum(0);
                row[0] = ((t * 4 + 8) >> 4) as u8;
                row[1] = ((t * 4 + 7) >> 4) as u8;
            } else {
                for x in 0..cw {
                    let t = colsum(x);
                    let last = if x == 0 { None } else { Some(colsum(x - 1)) };
                    let next = if x + 1 < cw {
                        Some(colsum(x + 1))
                    } else {
                        None
                    };
                    row[2 * x] = match last {
                        None => ((t * 4 + 8) >> 4) as u8,
                        Some(l) => ((t * 3 + l + 8) >> 4) as u8,
                    };
                    row[2 * x + 1] = match next {
                        None => ((t * 4 + 7) >> 4) as u8,
                        Some(n) => ((t * 3 + n + 7) >> 4) as u8,
                    };
                }
            }
            out[oy * width..(oy + 1) * width].copy_from_slice(&row[..width]);
        }
    }
    out
}

/// `jdcolor.c` YCbCr→RGB with its 16-bit fixed-point tables.
fn ycc_to_rgb(y: &[u8], ystride: usize, cb: &[u8], cr: &[u8], w: usize, h: usize, out: &mut [u8]) {
    const SCALEBITS: i64 = 16;
    const ONE_HALF: i64 = 1 << (SCALEBITS - 1);
    let fix = |x: f64| (x * f64::from(1u32 << SCALEBITS) + 0.5) as i64;
    let mut cr_r = [0i32; 256];
    let mut cb_b = [0i32; 256];
    let mut cr_g = [0i64; 256];
    let mut cb_g = [0i64; 256];
    for i in 0..256 {
        let x = i as i64 - 128;
        cr_r[i] = ((fix(1.40200) * x + ONE_HALF) >> SCALEBITS) as i32;
        cb_b[i] = ((fix(1.77200) * x + ONE_HALF) >> SCALEBITS) as i32;
        cr_g[i] = -fix(0.71414) * x;
        cb_g[i] = -fix(0.34414) * x + ONE_HALF;
    }
    let lim = |v: i32| v.clamp(0, 255) as u8;
    for yy in 0..h {
        for xx in 0..w {
            let yv = i32::from(y[yy * ystride + xx]);
            let (b, r) = (usize::from(cb[yy * w + xx]), usize::from(cr[yy * w + xx]));
            let o = (yy * w + xx) * 3;
            out[o] = lim(yv + cr_r[r]);
            out[o + 1] = lim(yv + ((cb_g[b] + cr_g[r]) >> SCALEBITS) as i32);
            out[o + 2] = lim(yv + cb_b[b]);
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn encode(img: &RgbImage, quality: u8) -> Vec<u8> {
        let mut buf = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, quality)
            .encode_image(img)
            .unwrap();
        buf
    }

    #[test]
    fn dc_only_block_is_flat() {
        // A DC coefficient of 8 with quantiser 2: pass 1 gives 16 << 2, pass 2 descales by 5:
        // (64 + 16) >> 5 = 2, plus the 128 level shift.
        let mut coef = [0i32; 64];
        coef[0] = 8;
        let q = [2u16; 64];
        let mut out = [0u8; 64];
        idct_islow(&coef, &q, &mut out, 8);
        assert!(out.iter().all(|&v| v == 130), "{out:?}");
    }

    #[test]
    fn range_limit_matches_libjpeg_table() {
        assert_eq!(idct_limit(0), 128);
        assert_eq!(idct_limit(127), 255);
        assert_eq!(idct_limit(300), 255);
        assert_eq!(idct_limit(-128), 0);
        assert_eq!(idct_limit(-400), 0);
        assert_eq!(idct_limit(-1), 127);
    }

    #[test]
    fn decodes_what_an_independent_encoder_wrote() {
        // Smooth colour gradients, odd size (partial MCUs); the `image` crate's encoder writes
        // 4:2:0 baseline JPEG. Decoding must come back close to the source and to the `image`
        // crate's own decoder (a different IDCT, so not bit-equal).
        let src = RgbImage::from_fn(61, 35, |x, y| {
            image::Rgb([(x * 4) as u8, (y * 7) as u8, ((x + y) * 2) as u8])
        });
        let bytes = encode(&src, 95);
        let ours = decode(&bytes).unwrap().expect("baseline 4:2:0 is in scope");
        let theirs = image::load_from_memory(&bytes).unwrap().to_rgb8();
        assert_eq!(ours.dimensions(), (61, 35));
        let max_diff = |a: &RgbImage, b: &RgbImage| {
            a.as_raw()
                .iter()
                .zip(b.as_raw())
                .map(|(&p, &q)| p.abs_diff(q))
                .max()
                .unwrap()
        };
        assert!(
            max_diff(&ours, &theirs) <= 4,
            "vs image crate: {}",
            max_diff(&ours, &theirs)
        );
        assert!(
            max_diff(&ours, &src) <= 12,
            "vs source: {}",
            max_diff(&ours, &src)
        );
    }

    #[test]
    fn corrupt_or_foreign_streams_are_reported() {
        assert!(decode(b"not a jpeg").is_err());
        let src = RgbImage::from_pixel(16, 16, image::Rgb([10, 20, 30]));
        let bytes = encode(&src, 90);
        // Truncated entropy data: libjpeg pads with zeros and still returns a full image.
        let cut = decode(&bytes[..bytes.len() - 6]).unwrap().unwrap();
        assert_eq!(cut.dimensions(), (16, 16));
        // Truncated inside the header: an error, never a panic.
        assert!(decode(&bytes[..40]).is_err());
    }
}
