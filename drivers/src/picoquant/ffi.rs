//! The vendor library, loaded at run time: PicoQuant's one module with `unsafe` code
//! (NI-DAQmx's is `daqmx/ffi.rs`). It looks up each C function of the histogram-mode API by its
//! documented name (`MH_…` or `HH_…`) with the prototype of the vendor's header
//! (`mhlib.h` 3.1, `hhlib.h` 3.0), and wraps each call in a safe method that owns every
//! buffer the library writes into. Return codes come back unchanged (`Err(code)` for a
//! negative one); what they mean is the driver's business.
//!
//! On Linux the headers define `_stdcall` as nothing, so the functions use the C
//! calling convention.
#![allow(unsafe_code)]

use std::ffi::{c_char, c_double, c_int, c_uint};
use std::path::Path;

use libloading::Library;

use super::defin::MAX_HIST_LEN;
use super::family::Family;

type FnText = unsafe extern "C" fn(*mut c_char) -> c_int;
type FnErrorText = unsafe extern "C" fn(*mut c_char, c_int) -> c_int;
type FnDev = unsafe extern "C" fn(c_int) -> c_int;
type FnDevText = unsafe extern "C" fn(c_int, *mut c_char) -> c_int;
type FnDevInt = unsafe extern "C" fn(c_int, c_int) -> c_int;
type FnDevInt2 = unsafe extern "C" fn(c_int, c_int, c_int) -> c_int;
type FnDevInt3 = unsafe extern "C" fn(c_int, c_int, c_int, c_int) -> c_int;
type FnDevOutInt = unsafe extern "C" fn(c_int, *mut c_int) -> c_int;
type FnDevIntOutInt = unsafe extern "C" fn(c_int, c_int, *mut c_int) -> c_int;
type FnDevOutDouble = unsafe extern "C" fn(c_int, *mut c_double) -> c_int;
type FnHardwareInfo = unsafe extern "C" fn(c_int, *mut c_char, *mut c_char, *mut c_char) -> c_int;
type FnWarningsText = unsafe extern "C" fn(c_int, *mut c_char, c_int) -> c_int;
type FnHistogramMh = unsafe extern "C" fn(c_int, *mut c_uint, c_int) -> c_int;
type FnHistogramHh = unsafe extern "C" fn(c_int, *mut c_uint, c_int, c_int) -> c_int;

/// Text buffers: larger than any the headers ask for (8 bytes for versions and serial
/// numbers, 24 to 32 for the model, 40 for an error string), so the library never
/// writes past them. The warnings text needs the 16,384 bytes the header asks for.
const TEXT: usize = 64;
const WARNINGS_TEXT: usize = 16_384;

/// `GetHistogram` with or without HHLib's `clear` argument.
#[derive(Clone, Copy)]
enum GetHistogram {
    Mh(FnHistogramMh),
    Hh(FnHistogramHh),
}

/// The library's functions. Plain function pointers copied out of the library: valid
/// for the process's life, which the library stays loaded for (`crate::resident`).
struct Api {
    get_library_version: FnText,
    get_error_string: FnErrorText,
    open_device: FnDevText,
    close_device: FnDev,
    initialize: FnDevInt2,
    get_hardware_info: FnHardwareInfo,
    get_serial_number: FnDevText,
    get_num_of_input_channels: FnDevOutInt,
    calibrate: Option<FnDev>,
    set_sync_div: FnDevInt,
    set_sync_trigger: FnDevInt2,
    set_sync_channel_offset: FnDevInt,
    set_input_trigger: FnDevInt3,
    set_input_channel_offset: FnDevInt2,
    set_input_channel_enable: FnDevInt2,
    set_histo_len: FnDevIntOutInt,
    set_binning: FnDevInt,
    set_offset: FnDevInt,
    get_resolution: FnDevOutDouble,
    get_sync_rate: FnDevOutInt,
    get_count_rate: FnDevIntOutInt,
    clear_hist_mem: FnDev,
    start_meas: FnDevInt,
    stop_meas: FnDev,
    ctc_status: FnDevOutInt,
    get_histogram: GetHistogram,
    get_flags: FnDevOutInt,
    get_warnings: FnDevOutInt,
    get_warnings_text: FnWarningsText,
    get_elapsed_meas_time: FnDevOutDouble,
}

/// A loaded PicoQuant library of one [`Family`].
pub(crate) struct Lib {
    api: Api,
}

/// Why a library could not be used.
#[derive(Debug)]
pub(crate) enum LoadError {
    /// `dlopen` failed (no such file, wrong architecture, missing dependency).
    Open(String),
    /// A function of the API is missing (another library, or too old a version).
    Missing(String, String),
}

/// Reads a NUL-terminated string the library wrote into `buf` (all of `buf` if it
/// holds no NUL).
fn text(buf: &[u8]) -> String {
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    String::from_utf8_lossy(&buf[..end]).trim().to_owned()
}

/// `Ok(())` for a non-negative return code, `Err(code)` otherwise.
fn check(code: c_int) -> Result<(), i32> {
    if code < 0 { Err(code) } else { Ok(()) }
}

impl Lib {
    /// Loads the library at `path` and looks up every function the driver calls.
    pub(crate) fn load(family: Family, path: &Path) -> Result<Lib, LoadError> {
        // Kept loaded for the process's life (`crate::resident`): never unloaded
        // under a task or thread of the library's own.
        let library = crate::resident::resident(path, || {
            // SAFETY: loading runs the library's initialisers. The path is the vendor
            // library the operator configured for this instrument (or the test
            // stand-in exporting the same API); nothing else is loaded here.
            unsafe { Library::new(path) }.map_err(|e| e.to_string())
        })
        .map_err(LoadError::Open)?;
        let prefix = family.prefix();
        macro_rules! get {
            ($name:literal) => {{
                let name = format!("{prefix}{}", $name);
                // SAFETY: the symbol's type is the prototype the vendor's header
                // declares for this name (see the type aliases above); `library` stays
                // loaded for the process's life (`crate::resident`).
                let symbol = unsafe { library.get(name.as_bytes()) }
                    .map_err(|e| LoadError::Missing(name.clone(), e.to_string()))?;
                *symbol
            }};
        }
        let api = Api {
            get_library_version: get!("GetLibraryVersion"),
            get_error_string: get!("GetErrorString"),
            open_device: get!("OpenDevice"),
            close_device: get!("CloseDevice"),
            initialize: get!("Initialize"),
            get_hardware_info: get!("GetHardwareInfo"),
            get_serial_number: get!("GetSerialNumber"),
            get_num_of_input_channels: get!("GetNumOfInputChannels"),
            calibrate: if family.calibrates() {
                Some(get!("Calibrate"))
            } else {
                None
            },
            set_sync_div: get!("SetSyncDiv"),
            set_sync_trigger: if family.uses_cfd() {
                get!("SetSyncCFD")
            } else {
                get!("SetSyncEdgeTrg")
            },
            set_sync_channel_offset: get!("SetSyncChannelOffset"),
            set_input_trigger: if family.uses_cfd() {
                get!("SetInputCFD")
            } else {
                get!("SetInputEdgeTrg")
            },
            set_input_channel_offset: get!("SetInputChannelOffset"),
            set_input_channel_enable: get!("SetInputChannelEnable"),
            set_histo_len: get!("SetHistoLen"),
            set_binning: get!("SetBinning"),
            set_offset: get!("SetOffset"),
            get_resolution: get!("GetResolution"),
            get_sync_rate: get!("GetSyncRate"),
            get_count_rate: get!("GetCountRate"),
            clear_hist_mem: get!("ClearHistMem"),
            start_meas: get!("StartMeas"),
            stop_meas: get!("StopMeas"),
            ctc_status: get!("CTCStatus"),
            get_histogram: match family {
                Family::MultiHarp => GetHistogram::Mh(get!("GetHistogram")),
                Family::HydraHarp => GetHistogram::Hh(get!("GetHistogram")),
            },
            get_flags: get!("GetFlags"),
            get_warnings: get!("GetWarnings"),
            get_warnings_text: get!("GetWarningsText"),
            get_elapsed_meas_time: get!("GetElapsedMeasTime"),
        };
        Ok(Lib { api })
    }

    /// A call that takes only the device index.
    fn dev(&self, f: FnDev, dev: i32) -> Result<(), i32> {
        // SAFETY: `f` takes one int and touches no memory of ours.
        check(unsafe { f(dev) })
    }

    /// A call that reads back one int.
    fn out_int(&self, f: FnDevOutInt, dev: i32) -> Result<i32, i32> {
        let mut v: c_int = 0;
        // SAFETY: the library writes one int through the pointer, which points at a
        // live local.
        check(unsafe { f(dev, &mut v) })?;
        Ok(v)
    }

    /// A call that reads back one double.
    fn out_double(&self, f: FnDevOutDouble, dev: i32) -> Result<f64, i32> {
        let mut v: c_double = 0.0;
        // SAFETY: the library writes one double through the pointer, which points at
        // a live local.
        check(unsafe { f(dev, &mut v) })?;
        Ok(v)
    }

    /// A call that writes a short string for device `dev`.
    fn dev_text(&self, f: FnDevText, dev: i32) -> Result<String, i32> {
        let mut buf = [0u8; TEXT];
        // SAFETY: the library writes a NUL-terminated string of at most the header's
        // size (8 bytes for a serial number), well inside the 64-byte buffer.
        check(unsafe { f(dev, buf.as_mut_ptr().cast()) })?;
        Ok(text(&buf))
    }

    /// `GetLibraryVersion`.
    pub(crate) fn library_version(&self) -> Result<String, i32> {
        let mut buf = [0u8; TEXT];
        // SAFETY: the library writes its version, an 8-byte string at most, into the
        // 64-byte buffer.
        check(unsafe { (self.api.get_library_version)(buf.as_mut_ptr().cast()) })?;
        Ok(text(&buf))
    }

    /// `GetErrorString`: the library's own words for `code`.
    pub(crate) fn error_string(&self, code: i32) -> String {
        let mut buf = [0u8; TEXT];
        // SAFETY: the header asks for a 40-byte buffer; this one has 64.
        let r = unsafe { (self.api.get_error_string)(buf.as_mut_ptr().cast(), code) };
        if r < 0 {
            return format!("unknown error {code}");
        }
        text(&buf)
    }

    /// `OpenDevice`: the serial number of the device at `dev`.
    pub(crate) fn open_device(&self, dev: i32) -> Result<String, i32> {
        self.dev_text(self.api.open_device, dev)
    }

    /// `CloseDevice`.
    pub(crate) fn close_device(&self, dev: i32) -> Result<(), i32> {
        self.dev(self.api.close_device, dev)
    }

    /// `Initialize(dev, mode, refsource)`.
    pub(crate) fn initialize(&self, dev: i32, mode: i32, refsource: i32) -> Result<(), i32> {
        // SAFETY: three ints, no memory.
        check(unsafe { (self.api.initialize)(dev, mode, refsource) })
    }

    /// `GetHardwareInfo`: model, part number, version.
    pub(crate) fn hardware_info(&self, dev: i32) -> Result<(String, String, String), i32> {
        let (mut model, mut part, mut version) = ([0u8; TEXT], [0u8; TEXT], [0u8; TEXT]);
        // SAFETY: the library writes three NUL-terminated strings (at most 24, 8 and 8
        // bytes per the headers) into three 64-byte buffers.
        check(unsafe {
            (self.api.get_hardware_info)(
                dev,
                model.as_mut_ptr().cast(),
                part.as_mut_ptr().cast(),
                version.as_mut_ptr().cast(),
            )
        })?;
        Ok((text(&model), text(&part), text(&version)))
    }

    /// `GetSerialNumber`.
    pub(crate) fn serial_number(&self, dev: i32) -> Result<String, i32> {
        self.dev_text(self.api.get_serial_number, dev)
    }

    /// `GetNumOfInputChannels`.
    pub(crate) fn input_channels(&self, dev: i32) -> Result<i32, i32> {
        self.out_int(self.api.get_num_of_input_channels, dev)
    }

    /// `HH_Calibrate` (nothing to do for a family that does not calibrate).
    pub(crate) fn calibrate(&self, dev: i32) -> Result<(), i32> {
        match self.api.calibrate {
            Some(f) => self.dev(f, dev),
            None => Ok(()),
        }
    }

    /// `SetSyncDiv`.
    pub(crate) fn set_sync_div(&self, dev: i32, div: i32) -> Result<(), i32> {
        // SAFETY: two ints, no memory.
        check(unsafe { (self.api.set_sync_div)(dev, div) })
    }

    /// `SetSyncEdgeTrg(level, edge)` or `SetSyncCFD(level, zero cross)`.
    pub(crate) fn set_sync_trigger(&self, dev: i32, level: i32, edge_or_zc: i32) -> Result<(), i32> {
        // SAFETY: three ints, no memory.
        check(unsafe { (self.api.set_sync_trigger)(dev, level, edge_or_zc) })
    }

    /// `SetSyncChannelOffset`, ps.
    pub(crate) fn set_sync_channel_offset(&self, dev: i32, ps: i32) -> Result<(), i32> {
        // SAFETY: two ints, no memory.
        check(unsafe { (self.api.set_sync_channel_offset)(dev, ps) })
    }

    /// `SetInputEdgeTrg(channel, level, edge)` or `SetInputCFD(channel, level, zc)`.
    pub(crate) fn set_input_trigger(
        &self,
        dev: i32,
        ch: i32,
        level: i32,
        edge_or_zc: i32,
    ) -> Result<(), i32> {
        // SAFETY: four ints, no memory.
        check(unsafe { (self.api.set_input_trigger)(dev, ch, level, edge_or_zc) })
    }

    /// `SetInputChannelOffset`, ps.
    pub(crate) fn set_input_channel_offset(&self, dev: i32, ch: i32, ps: i32) -> Result<(), i32> {
        // SAFETY: three ints, no memory.
        check(unsafe { (self.api.set_input_channel_offset)(dev, ch, ps) })
    }

    /// `SetInputChannelEnable`.
    pub(crate) fn set_input_channel_enable(&self, dev: i32, ch: i32, on: bool) -> Result<(), i32> {
        // SAFETY: three ints, no memory.
        check(unsafe { (self.api.set_input_channel_enable)(dev, ch, i32::from(on)) })
    }

    /// `SetHistoLen`: the histogram length the code gives.
    pub(crate) fn set_histo_len(&self, dev: i32, len_code: i32) -> Result<i32, i32> {
        let mut actual: c_int = 0;
        // SAFETY: the library writes one int through a pointer to a live local.
        check(unsafe { (self.api.set_histo_len)(dev, len_code, &mut actual) })?;
        Ok(actual)
    }

    /// `SetBinning`.
    pub(crate) fn set_binning(&self, dev: i32, binning: i32) -> Result<(), i32> {
        // SAFETY: two ints, no memory.
        check(unsafe { (self.api.set_binning)(dev, binning) })
    }

    /// `SetOffset`, ns.
    pub(crate) fn set_offset(&self, dev: i32, ns: i32) -> Result<(), i32> {
        // SAFETY: two ints, no memory.
        check(unsafe { (self.api.set_offset)(dev, ns) })
    }

    /// `GetResolution`: the bin width in force, ps.
    pub(crate) fn resolution(&self, dev: i32) -> Result<f64, i32> {
        self.out_double(self.api.get_resolution, dev)
    }

    /// `GetSyncRate`, Hz.
    pub(crate) fn sync_rate(&self, dev: i32) -> Result<i32, i32> {
        self.out_int(self.api.get_sync_rate, dev)
    }

    /// `GetCountRate` of input `ch`, Hz.
    pub(crate) fn count_rate(&self, dev: i32, ch: i32) -> Result<i32, i32> {
        let mut rate: c_int = 0;
        // SAFETY: the library writes one int through a pointer to a live local.
        check(unsafe { (self.api.get_count_rate)(dev, ch, &mut rate) })?;
        Ok(rate)
    }

    /// `ClearHistMem`.
    pub(crate) fn clear_hist_mem(&self, dev: i32) -> Result<(), i32> {
        self.dev(self.api.clear_hist_mem, dev)
    }

    /// `StartMeas`, acquisition time in ms.
    pub(crate) fn start_meas(&self, dev: i32, ms: i32) -> Result<(), i32> {
        // SAFETY: two ints, no memory.
        check(unsafe { (self.api.start_meas)(dev, ms) })
    }

    /// `StopMeas`.
    pub(crate) fn stop_meas(&self, dev: i32) -> Result<(), i32> {
        self.dev(self.api.stop_meas, dev)
    }

    /// `CTCStatus`: whether the acquisition time has run out.
    pub(crate) fn ctc_done(&self, dev: i32) -> Result<bool, i32> {
        Ok(self.out_int(self.api.ctc_status, dev)? != 0)
    }

    /// `GetHistogram` of input `ch` into `counts`, which is first made
    /// [`MAX_HIST_LEN`] long: the longest histogram any length code gives, so the
    /// library can never write past it. HHLib's `clear` argument is 0 (the driver
    /// clears the memory before each acquisition).
    pub(crate) fn histogram(&self, dev: i32, ch: i32, counts: &mut Vec<u32>) -> Result<(), i32> {
        counts.clear();
        counts.resize(MAX_HIST_LEN, 0);
        let ptr: *mut c_uint = counts.as_mut_ptr();
        // SAFETY: the library writes the current histogram length's worth of unsigned
        // ints, at most MAXHISTLEN (65,536), into a buffer of exactly that many.
        let r = unsafe {
            match self.api.get_histogram {
                GetHistogram::Mh(f) => f(dev, ptr, ch),
                GetHistogram::Hh(f) => f(dev, ptr, ch, 0),
            }
        };
        check(r)
    }

    /// `GetFlags`.
    pub(crate) fn flags(&self, dev: i32) -> Result<i32, i32> {
        self.out_int(self.api.get_flags, dev)
    }

    /// `GetWarnings` (meaningful after the count rates were read).
    pub(crate) fn warnings(&self, dev: i32) -> Result<i32, i32> {
        self.out_int(self.api.get_warnings, dev)
    }

    /// `GetWarningsText` for the bits `warnings`.
    pub(crate) fn warnings_text(&self, dev: i32, warnings: i32) -> Result<String, i32> {
        let mut buf = vec![0u8; WARNINGS_TEXT];
        // SAFETY: the header asks for a 16,384-byte buffer; this is one.
        check(unsafe { (self.api.get_warnings_text)(dev, buf.as_mut_ptr().cast(), warnings) })?;
        Ok(text(&buf))
    }

    /// `GetElapsedMeasTime`, ms.
    pub(crate) fn elapsed_ms(&self, dev: i32) -> Result<f64, i32> {
        self.out_double(self.api.get_elapsed_meas_time, dev)
    }
}
