//! How a process that runs this maths sets itself up: its floating-point mode and its heap.
//!
//! Every canopy process calls both at start ([`flush_subnormals_to_zero`], [`tune_allocator`]),
//! and so do the benchmarks, so that canopy's code and the raw-library references they are
//! compared with run alike, and as in production. No I/O: process-wide CPU and allocator
//! settings only.

/// Makes this thread (and every thread it starts later: they inherit the floating-point control
/// state) treat subnormal numbers as zero: flush-to-zero and denormals-are-zero in MXCSR on
/// x86_64, FZ in FPCR on aarch64; nothing elsewhere.
///
/// Why: faer's matrix kernels compute on the padding lanes of their packed panels (uninitialised
/// scratch, whatever an earlier product left there) and discard the results. When those lanes
/// hold subnormal bit patterns every FMA on them takes a microcode assist (~100× slower on
/// Intel). Measured in a vehicle at ~100 features: a 9×270 by 270×300 product while augmenting
/// three fused features took 4 ms instead of 0.03 ms, which made fusing a received batch cost
/// 7–14 ms instead of 2–3 ms (same product with FTZ/DAZ: 0.03 ms). The inputs themselves were
/// all normal (smallest |entry| 1e-14). Values below 2.2e-308 carry nothing this estimator can
/// use, so flushing them changes no figure; the deterministic simulation stays reproducible
/// (the mode is the same on every run).
pub fn flush_subnormals_to_zero() {
    #[cfg(target_arch = "x86_64")]
    {
        // MXCSR bits: FTZ = 15, DAZ = 6.
        let mut csr: u32 = 0;
        #[allow(unsafe_code)]
        // SAFETY: stmxcsr/ldmxcsr read and write this thread's SSE control register through a
        // valid pointer to a local; only the FTZ and DAZ mode bits are changed (no exception is
        // unmasked, rounding is unchanged).
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack));
            csr |= (1 << 15) | (1 << 6);
            std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack, readonly));
        }
    }
    #[cfg(target_arch = "aarch64")]
    {
        let mut fpcr: u64;
        #[allow(unsafe_code)]
        // SAFETY: reads and writes this thread's FPCR; only the FZ bit (24) is set.
        unsafe {
            std::arch::asm!("mrs {}, fpcr", out(reg) fpcr, options(nomem, nostack));
            fpcr |= 1 << 24;
            std::arch::asm!("msr fpcr, {}", in(reg) fpcr, options(nomem, nostack));
        }
    }
}

/// Whether [`flush_subnormals_to_zero`] is in effect on this thread (x86_64, aarch64).
pub fn subnormals_flushed() -> bool {
    let tiny = std::hint::black_box(f64::MIN_POSITIVE);
    // With flush-to-zero, a product that would be subnormal is 0.
    std::hint::black_box(tiny * 0.5) == 0.0
}

/// Heap blocks of this many bytes or more are `mmap`ped, and unmapped when freed
/// ([`tune_allocator`]; the [`HeapPolicy::Lean`] threshold).
pub const MMAP_THRESHOLD: usize = 4 << 20;

/// The [`HeapPolicy::Warm`] threshold: glibc's largest (`DEFAULT_MMAP_THRESHOLD_MAX` on 64-bit),
/// so that a k × k matrix up to 32 MiB (k ≈ 2 000, ~660 features) comes from the arenas.
pub const WARM_MMAP_THRESHOLD: usize = 32 << 20;

/// What the heap keeps between fusion rounds: a process-wide choice of memory against CPU.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HeapPolicy {
    /// Matrices of [`MMAP_THRESHOLD`] (4 MiB) and more are `mmap`ped and returned to the kernel
    /// when freed, and the arenas are trimmed after each round ([`heap_slack`]): the least
    /// resident memory, paid for with a page fault and the kernel's zeroing per 4 KiB of every
    /// fresh k × k temporary, every round (tree-8 with exact links: peak RSS ≤ 300 MB per
    /// vehicle, issue 15).
    #[default]
    Lean,
    /// Matrices up to [`WARM_MMAP_THRESHOLD`] (32 MiB) come from the arenas and stay there for
    /// the next round: the temporaries are reused warm. Measured on tree-8 with 128 kB/s radio
    /// links (300 s, `canopy run`): system time 87 → 14–20 s, page faults ~40 M → 1.2–6.2 M,
    /// real-time factor 0.92–0.97 → 1.11–1.21, largest vehicle RSS 241 → 324–408 MB
    /// (docs/benchmarks.md, twelfth pass). Beyond ~660 features the k × k blocks exceed the
    /// threshold and are `mmap`ped as with `Lean`.
    Warm,
}

impl HeapPolicy {
    /// The `mmap` threshold of the policy [bytes].
    pub fn mmap_threshold(self) -> usize {
        match self {
            HeapPolicy::Lean => MMAP_THRESHOLD,
            HeapPolicy::Warm => WARM_MMAP_THRESHOLD,
        }
    }
}

/// The threshold in effect ([`set_heap_policy`]; what [`heap_slack`] compares blocks with).
static THRESHOLD: std::sync::atomic::AtomicUsize =
    std::sync::atomic::AtomicUsize::new(MMAP_THRESHOLD);

/// Switches the process to `policy` ([`HeapPolicy`]); [`tune_allocator`] sets `Lean`. Called
/// by the vehicle process and `canopy sim` once the scenario is known (glibc's `mallopt`
/// takes the allocator's lock: safe with other threads running).
pub fn set_heap_policy(policy: HeapPolicy) {
    let t = policy.mmap_threshold();
    THRESHOLD.store(t, std::sync::atomic::Ordering::Relaxed);
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        #[allow(unsafe_code)]
        // SAFETY: mallopt only sets an allocator parameter, under the allocator's lock.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, t as libc::c_int);
        }
    }
}

/// Keeps freed heap memory mapped instead of returning it to the kernel (glibc `mallopt`),
/// except for the largest blocks.
///
/// Why: a fusion round allocates and frees several k×k matrices (k = 3 × features; 1.8 MB at
/// 160 features). With glibc's defaults such blocks are `mmap`ped and unmapped every time, and
/// every round then pays a page fault per 4 KiB touched plus the kernel's zeroing: perf showed
/// ~10 % of a vehicle process in page faults and memset. Serving them from a heap that is never
/// trimmed makes the memory reused warm.
///
/// Blocks of [`MMAP_THRESHOLD`] and more are still `mmap`ped: a heap that is never trimmed
/// keeps its peak, and matrices that grow a little every round (the map grows) fragment it, so
/// that a vehicle at 324 features held 250 MB of anonymous memory for ~60 MB of live matrices
/// (issue 15). Above 4 MiB (k ≳ 720, ~240 features) a page fault per 4 KiB is small next to the
/// O(k²)–O(k³) work on the block, and a freed block goes back to the kernel at once.
/// No effect on other C libraries.
pub fn tune_allocator() {
    set_heap_policy(HeapPolicy::Lean);
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        #[allow(unsafe_code)]
        // SAFETY: mallopt only sets allocator parameters; it is called before any thread of
        // this process allocates concurrently (first thing in the command dispatch).
        unsafe {
            libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
        }
    }
}

/// Free heap memory the arenas may keep beyond what the next fusion round reuses
/// ([`heap_slack`]).
pub const HEAP_SLACK: usize = 8 << 20;

/// How much free heap memory to keep after a fusion round on a map of `features` features:
/// [`HEAP_SLACK`], plus, while a k × k matrix (k = 3 × features) is below
/// [`MMAP_THRESHOLD`] and so comes from the arenas, room for the dozen k × k temporaries of
/// the next round (kept warm: trimming them would make every round fault them in again).
pub fn heap_slack(features: usize) -> usize {
    let k = 3 * features;
    let block = 8 * k * k;
    if block < THRESHOLD.load(std::sync::atomic::Ordering::Relaxed) {
        HEAP_SLACK + 12 * block
    } else {
        HEAP_SLACK
    }
}

/// Returns the free memory of every heap arena to the kernel (glibc `malloc_trim`) when they
/// hold more than `slack` bytes free (`mallinfo2`); true when it trimmed. No effect on other C
/// libraries.
///
/// Why: heap memory is kept mapped when freed ([`tune_allocator`]), so that a round's k × k
/// temporaries are warm the next round. Once the map is large enough for those temporaries to be
/// `mmap`ped ([`MMAP_THRESHOLD`]) the arenas still hold the high-water mark of the rounds
/// before, which nothing reuses: at 324 features a vehicle with three neighbours held 93 MB in
/// its two arenas for ~38 MB of live matrices (docs/benchmarks.md). Called after each fusion
/// round with [`heap_slack`], it keeps what the next round reuses and returns the rest.
pub fn trim_heap(slack: usize) -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        #[allow(unsafe_code)]
        // SAFETY: mallinfo2 only reads the allocator's statistics (taking each arena's lock);
        // malloc_trim only releases free pages of the arenas; both are thread-safe.
        unsafe {
            let free = libc::mallinfo2().fordblks;
            if free > slack {
                libc::malloc_trim(0);
                return true;
            }
        }
    }
    let _ = slack;
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The slack keeps a round's temporaries while they come from the arenas, and only the
    /// fixed slack once they are `mmap`ped; trimming with no slack at all is harmless.
    #[test]
    fn heap_slack_follows_the_mmap_threshold() {
        // 100 features: k × k = 0.72 MB, from the arenas.
        assert_eq!(heap_slack(100), HEAP_SLACK + 12 * 8 * 300 * 300);
        // 324 features: 7.6 MB, mmapped.
        assert_eq!(heap_slack(324), HEAP_SLACK);
        let held: Vec<Vec<u8>> = (0..64).map(|i| vec![i as u8; 1 << 16]).collect();
        drop(held);
        let _ = trim_heap(0);
        let v = vec![1u8; 1 << 20];
        assert_eq!(v.iter().map(|&b| usize::from(b)).sum::<usize>(), 1 << 20);
    }

    /// The mode takes effect on the calling thread and is inherited by the threads it starts
    /// (the process roles start tokio and worker threads after setting it); a thread that did
    /// not set it keeps gradual underflow. Run in fresh threads so other tests are unaffected.
    #[test]
    fn flush_to_zero_is_set_and_inherited() {
        std::thread::spawn(|| {
            assert!(!subnormals_flushed(), "default mode already flushes");
            flush_subnormals_to_zero();
            if cfg!(any(target_arch = "x86_64", target_arch = "aarch64")) {
                assert!(subnormals_flushed());
                let child = std::thread::spawn(subnormals_flushed).join().unwrap();
                assert!(
                    child,
                    "a thread started afterwards does not inherit the mode"
                );
            }
        })
        .join()
        .unwrap();
    }
}
