//! Bounds of the size flags, checked when the command line is parsed: an absurd size is an
//! error naming the flag (clap prints "invalid value '100000' for '--resolution …'") before
//! anything is allocated, instead of an allocation failure that aborts the process.

fn in_range(text: &str, min: usize, max: usize) -> Result<usize, String> {
    let v: usize = text
        .trim()
        .parse()
        .map_err(|_| format!("{} is not a whole number", f3g_io::quoted(text)))?;
    if !(min..=max).contains(&v) {
        return Err(format!("{v} is not in {min}..={max}"));
    }
    Ok(v)
}

/// A whole number in `MIN..=MAX`.
pub fn size<const MIN: usize, const MAX: usize>(text: &str) -> Result<usize, String> {
    in_range(text, MIN, MAX)
}

/// An image side in pixels in `MIN..=MAX` (the cameras' `u32`).
pub fn side<const MIN: u32, const MAX: u32>(text: &str) -> Result<u32, String> {
    in_range(text, MIN as usize, MAX as usize).map(|v| v as u32)
}

/// An image size `WIDTHxHEIGHT`, 16–8192 pixels a side.
pub fn image_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text
        .split_once('x')
        .ok_or_else(|| format!("{}: expected WIDTHxHEIGHT", f3g_io::quoted(text)))?;
    Ok((side::<16, 8192>(w)?, side::<16, 8192>(h)?))
}

/// A benchmark image size: `N` (square) or `WIDTHxHEIGHT`, 16–8192 pixels a side.
pub fn resolution(text: &str) -> Result<(u32, u32), String> {
    if text.contains('x') {
        image_size(text)
    } else {
        side::<16, 8192>(text).map(|n| (n, n))
    }
}

/// A scale factor of the capture's resolution for evaluation, `0.01..=4` (beyond 4 the body
/// images of ordinary captures would exceed the renderer's image-size limit).
pub fn eval_scale(text: &str) -> Result<f32, String> {
    let v: f32 = text
        .trim()
        .parse()
        .map_err(|_| format!("{} is not a number", f3g_io::quoted(text)))?;
    if !(0.01..=4.0).contains(&v) {
        return Err(format!(
            "{} is not in 0.01..=4",
            f3g_io::quoted(text.trim())
        ));
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_outside_the_range_are_errors_that_say_the_range() {
        assert_eq!(size::<16, 8192>("512"), Ok(512));
        assert_eq!(
            size::<16, 8192>("100000").unwrap_err(),
            "100000 is not in 16..=8192"
        );
        assert!(size::<16, 8192>("-1").unwrap_err().contains("whole number"));
        assert_eq!(side::<16, 8192>("8192"), Ok(8192));
        assert!(side::<16, 8192>("8193").is_err());
        assert_eq!(image_size("48x64"), Ok((48, 64)));
        assert!(image_size("48x100000").unwrap_err().contains("16..=8192"));
        assert!(image_size("48").unwrap_err().contains("WIDTHxHEIGHT"));
        assert_eq!(eval_scale("0.5"), Ok(0.5));
        for bad in ["0", "inf", "NaN", "1e9"] {
            assert!(eval_scale(bad).unwrap_err().contains("0.01..=4"), "{bad}");
        }
    }
}
