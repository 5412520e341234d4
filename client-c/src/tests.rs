//! The C API's failures: status codes, the last error's message, and an origin kept or refused.

#![allow(clippy::unwrap_used, clippy::undocumented_unsafe_blocks)]
use super::*;

fn last() -> String {
    unsafe { CStr::from_ptr(insitu_last_error()) }
        .to_string_lossy()
        .into_owned()
}

#[test]
fn failures_return_codes_and_name_the_problem() {
    let mut c: *mut InsituClient = std::ptr::null_mut();
    let addr = CString::new("127.0.0.1:1").unwrap();
    let s = unsafe { insitu_connect(addr.as_ptr(), std::ptr::null(), &mut c) };
    assert_eq!(s, InsituStatus::Unreachable);
    assert!(last().contains("127.0.0.1:1"), "{}", last());
    assert!(c.is_null());
    let s = unsafe { insitu_connect(std::ptr::null(), std::ptr::null(), &mut c) };
    assert_eq!(s, InsituStatus::InvalidArgument);
    assert_eq!(last(), "addr is null");
    let dims = [2u32, 2, 2];
    let data = [0f32; 8];
    let s = unsafe {
        insitu_push_step(
            std::ptr::null(),
            0,
            0.0,
            data.as_ptr().cast(),
            32,
            4,
            dims.as_ptr(),
            [0u32; 3].as_ptr(),
            dims.as_ptr(),
            std::ptr::null(),
            0,
            1,
            std::ptr::null_mut(),
        )
    };
    assert_eq!(s, InsituStatus::InvalidArgument);
    assert_eq!(last(), "client is null");
    // A buffer shorter than the brick is refused before it is read.
    let s = unsafe {
        insitu_push_step(
            std::ptr::null(),
            0,
            0.0,
            data.as_ptr().cast(),
            16,
            5,
            dims.as_ptr(),
            [0u32; 3].as_ptr(),
            dims.as_ptr(),
            std::ptr::null(),
            0,
            1,
            std::ptr::null_mut(),
        )
    };
    assert_eq!(s, InsituStatus::InvalidArgument);
    assert!(
        last().contains(
            "data_bytes 16 is not the 64 bytes of a brick of [2, 2, 2] points of 8-byte values"
        ),
        "{}",
        last()
    );
    assert_eq!(
        unsafe { insitu_close(std::ptr::null_mut(), 1.0, std::ptr::null_mut()) },
        InsituStatus::Ok
    );
    let mut none: *mut InsituClient = std::ptr::null_mut();
    assert_eq!(
        unsafe { insitu_close(&mut none, 1.0, std::ptr::null_mut()) },
        InsituStatus::Ok
    );
}

/// The origin is kept for the pushes that follow; a null or non-finite one is refused and
/// the one in force stays.
#[test]
fn an_origin_is_kept_or_refused_by_name() {
    let c = InsituClient {
        rt: tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap(),
        client: Mutex::new(None),
        origin: Mutex::new([0.0; 3]),
    };
    let o = [100.0f32, -50.0, 7.0];
    assert_eq!(
        unsafe { insitu_set_origin(&c, o.as_ptr()) },
        InsituStatus::Ok
    );
    assert_eq!(*c.origin.lock().unwrap(), o);
    let bad = [0.0, f32::NAN, 0.0];
    assert_eq!(
        unsafe { insitu_set_origin(&c, bad.as_ptr()) },
        InsituStatus::InvalidArgument
    );
    assert!(
        last().contains("origin") && last().contains("finite"),
        "{}",
        last()
    );
    assert_eq!(
        unsafe { insitu_set_origin(&c, std::ptr::null()) },
        InsituStatus::InvalidArgument
    );
    assert_eq!(last(), "origin is null (need 3 values)");
    assert_eq!(
        unsafe { insitu_set_origin(std::ptr::null(), o.as_ptr()) },
        InsituStatus::InvalidArgument
    );
    assert_eq!(*c.origin.lock().unwrap(), o, "the origin in force stays");
}
