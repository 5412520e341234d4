//! The part of ADIOS2's C API (`adios2_c.h`, version 2.9 and later) the reader calls: an
//! ADIOS object, an IO with its engine and parameters, steps, variables (shape, type,
//! selections, gets, the blocks written) and attributes. Declared by hand, not generated: the API is stable and
//! these are its few calls.

#![allow(non_camel_case_types)]

use std::ffi::{c_char, c_float, c_int};

/// `adios2_adios`, `adios2_io`, `adios2_engine`, `adios2_variable`, `adios2_attribute`:
/// opaque handles owned by the library.
#[repr(C)]
pub struct adios2_adios {
    _private: [u8; 0],
}
#[repr(C)]
pub struct adios2_io {
    _private: [u8; 0],
}
#[repr(C)]
pub struct adios2_engine {
    _private: [u8; 0],
}
#[repr(C)]
pub struct adios2_variable {
    _private: [u8; 0],
}
#[repr(C)]
pub struct adios2_attribute {
    _private: [u8; 0],
}

/// `adios2_error`: 0 is success.
pub type adios2_error = c_int;
pub const ERROR_NONE: adios2_error = 0;

/// `adios2_mode`.
pub type adios2_mode = c_int;
pub const MODE_READ: adios2_mode = 2;
pub const MODE_READ_RANDOM_ACCESS: adios2_mode = 6;
pub const MODE_SYNC: adios2_mode = 5;

/// `adios2_step_mode`.
pub const STEP_MODE_READ: c_int = 2;

/// `adios2_step_status`.
pub type adios2_step_status = c_int;
pub const STEP_OK: adios2_step_status = 0;
pub const STEP_NOT_READY: adios2_step_status = 1;
pub const STEP_END_OF_STREAM: adios2_step_status = 2;

/// `adios2_type`.
pub type adios2_type = c_int;
pub const TYPE_STRING: adios2_type = 0;
pub const TYPE_FLOAT: adios2_type = 1;
pub const TYPE_DOUBLE: adios2_type = 2;
pub const TYPE_INT8: adios2_type = 5;
pub const TYPE_INT16: adios2_type = 6;
pub const TYPE_INT32: adios2_type = 7;
pub const TYPE_INT64: adios2_type = 8;
pub const TYPE_UINT8: adios2_type = 9;
pub const TYPE_UINT16: adios2_type = 10;
pub const TYPE_UINT32: adios2_type = 11;
pub const TYPE_UINT64: adios2_type = 12;

/// `adios2_shapeid`.
pub const SHAPE_GLOBAL_ARRAY: c_int = 1;

/// `union adios2_PrimitiveStdtypeUnion`: its largest member is a `long double` (16 bytes,
/// 16-aligned on x86-64 and aarch64); only its size and alignment matter here.
#[repr(C, align(16))]
pub struct adios2_union {
    _bytes: [u8; 16],
}

/// `adios2_blockinfo`: one block a writer put in a step (`Start`, `Count` in the variable's
/// own dimension order, `Dims` entries each).
#[repr(C)]
#[allow(non_snake_case)]
pub struct adios2_blockinfo {
    pub WriterID: c_int,
    pub BlockID: usize,
    pub Start: *mut usize,
    pub Count: *mut usize,
    pub MinUnion: adios2_union,
    pub MaxUnion: adios2_union,
    pub Value: adios2_union,
}

/// `adios2_varinfo`: a variable's blocks in a step.
#[repr(C)]
#[allow(non_snake_case)]
pub struct adios2_varinfo {
    pub Dims: c_int,
    pub Shape: *mut usize,
    pub IsValue: c_int,
    pub IsReverseDims: c_int,
    pub nblocks: usize,
    pub BlocksInfo: *mut adios2_blockinfo,
}

extern "C" {
    pub fn adios2_init_serial() -> *mut adios2_adios;
    pub fn adios2_inquire_blockinfo(
        engine: *mut adios2_engine,
        variable: *mut adios2_variable,
        step: usize,
    ) -> *mut adios2_varinfo;
    pub fn adios2_free_blockinfo(data_blocks: *mut adios2_varinfo);
    pub fn adios2_finalize(adios: *mut adios2_adios) -> adios2_error;
    pub fn adios2_declare_io(adios: *mut adios2_adios, name: *const c_char) -> *mut adios2_io;
    pub fn adios2_set_engine(io: *mut adios2_io, engine_type: *const c_char) -> adios2_error;
    pub fn adios2_set_parameter(
        io: *mut adios2_io,
        key: *const c_char,
        value: *const c_char,
    ) -> adios2_error;
    pub fn adios2_open(
        io: *mut adios2_io,
        name: *const c_char,
        mode: adios2_mode,
    ) -> *mut adios2_engine;
    pub fn adios2_close(engine: *mut adios2_engine) -> adios2_error;
    pub fn adios2_begin_step(
        engine: *mut adios2_engine,
        mode: c_int,
        timeout_seconds: c_float,
        status: *mut adios2_step_status,
    ) -> adios2_error;
    pub fn adios2_current_step(step: *mut usize, engine: *const adios2_engine) -> adios2_error;
    pub fn adios2_end_step(engine: *mut adios2_engine) -> adios2_error;
    pub fn adios2_get(
        engine: *mut adios2_engine,
        variable: *mut adios2_variable,
        data: *mut std::ffi::c_void,
        launch: adios2_mode,
    ) -> adios2_error;
    pub fn adios2_available_variables(io: *mut adios2_io, size: *mut usize) -> *mut *mut c_char;
    pub fn adios2_inquire_variable(io: *mut adios2_io, name: *const c_char)
        -> *mut adios2_variable;
    pub fn adios2_variable_ndims(
        ndims: *mut usize,
        variable: *const adios2_variable,
    ) -> adios2_error;
    pub fn adios2_variable_shape(
        shape: *mut usize,
        variable: *const adios2_variable,
    ) -> adios2_error;
    pub fn adios2_variable_shapeid(
        shapeid: *mut c_int,
        variable: *const adios2_variable,
    ) -> adios2_error;
    pub fn adios2_variable_type(
        t: *mut adios2_type,
        variable: *const adios2_variable,
    ) -> adios2_error;
    pub fn adios2_variable_steps(
        steps: *mut usize,
        variable: *const adios2_variable,
    ) -> adios2_error;
    pub fn adios2_set_selection(
        variable: *mut adios2_variable,
        ndims: usize,
        start: *const usize,
        count: *const usize,
    ) -> adios2_error;
    pub fn adios2_set_step_selection(
        variable: *mut adios2_variable,
        step_start: usize,
        step_count: usize,
    ) -> adios2_error;
    pub fn adios2_inquire_attribute(
        io: *mut adios2_io,
        name: *const c_char,
    ) -> *mut adios2_attribute;
    pub fn adios2_attribute_type(
        t: *mut adios2_type,
        attribute: *const adios2_attribute,
    ) -> adios2_error;
    pub fn adios2_attribute_size(
        size: *mut usize,
        attribute: *const adios2_attribute,
    ) -> adios2_error;
    pub fn adios2_attribute_data(
        data: *mut std::ffi::c_void,
        size: *mut usize,
        attribute: *const adios2_attribute,
    ) -> adios2_error;
    pub fn adios2_variable_steps_start(
        steps_start: *mut usize,
        variable: *const adios2_variable,
    ) -> adios2_error;
}

// Text attributes with their lengths asked first. Older libraries copy a string attribute
// into a buffer whose size they are not told, so this reader calls only these, where the
// build found them in the library's header (`build.rs`).
#[cfg(adios2_string_data)]
extern "C" {
    pub fn adios2_attribute_is_value(
        result: *mut c_int,
        attribute: *const adios2_attribute,
    ) -> adios2_error;
    pub fn adios2_attribute_string_data(
        attribute: *const adios2_attribute,
        data: *mut c_char,
        length: *mut usize,
    ) -> adios2_error;
    pub fn adios2_attribute_string_data_array(
        attribute: *const adios2_attribute,
        data: *mut *mut c_char,
        lengths: *mut usize,
    ) -> adios2_error;
}
