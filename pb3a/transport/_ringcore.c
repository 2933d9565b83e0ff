/* The hot path of ShmRing in C: header-word access with real memory ordering,
 * the scalar write, the drain loop and the reader's sleep hand-shake.
 *
 * Why C: a value crossing a link after an idle millisecond runs every step with
 * cold caches, where each Python operation costs microseconds; and CPython cannot
 * issue fences, so the pure-Python ring was correct on x86-64 (TSO) only. Here
 * the writer publishes `head` with a release store and the reader loads it with
 * an acquire load (records are visible before the head that covers them); the
 * reader hands bytes back with a release store of `tail`, which the writer loads
 * with acquire. The sleep hand-shake is Dekker's (store own flag, full fence,
 * load the other side's word), so a wake-up cannot be lost on any architecture.
 *
 * Layout (see ring.py): a 512-byte header of 64-bit words, one cache line
 * each, then `capacity` data bytes of 64-byte aligned records:
 *   u32 length | u16 kind | u16 meta length | u64 seq | f64 sent_at | ...
 * Ints and floats ride right after that 24-byte header in a 64-byte record.
 * A ring may also own a pool of equal slots for large arrays (see take_slot):
 *   ... | `slots` state words | page-aligned slots, `stride` bytes apart
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#include <errno.h>
#include <poll.h>
#include <stdint.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#define HEADER 512
#define W_CAP 1
#define W_SLOTS 2
#define W_SLOT_BYTES 3
#define W_HEAD 8
#define W_TAIL 16
#define W_RPOS 24
#define W_RSEQ 25     /* the sequence number after the last record read */
#define W_SEQ 32
#define W_WAITING 40
#define W_FLUSH 48    /* the writer (a lossless link closing): take everything now */
#define REC_HEAD 24
#define SCALAR_LEN 64
#define PAGE 4096ULL
#define MAX_SLOTS 4096
#define CLAIMED UINT64_MAX   /* a slot's state while a value is received into it */
enum { K_PAD = 0, K_INT = 4, K_FLOAT = 5, K_SLOT = 6 };

#define LOAD_ACQ(p) __atomic_load_n((p), __ATOMIC_ACQUIRE)
#define STORE_REL(p, v) __atomic_store_n((p), (v), __ATOMIC_RELEASE)
#define STORE_RLX(p, v) __atomic_store_n((p), (v), __ATOMIC_RELAXED)
#define FENCE() __atomic_thread_fence(__ATOMIC_SEQ_CST)

typedef struct {
    PyObject_HEAD
    Py_buffer view;          /* the whole segment; held until release() */
    uint64_t *words;         /* NULL once released */
    unsigned char *data;
    unsigned long long cap;
    uint64_t *states;        /* per slot: 0 free, else the seq of its record + 1 */
    unsigned char *pool;
    unsigned long long slots, slot_bytes, stride, pool_offset;
    /* the writer's private copies (only the writing process uses them) */
    unsigned long long head, published, seq, tail;
    /* the reader's */
    unsigned long long rpos;
    long long expected;      /* next sequence number expected, -1 before the first */
    int leases;              /* array views outstanding: the tail then moves in Python */
    int bell;                /* the reader's doorbell (eventfd) for the writer; -1: none */
} RingCore;

static double monotonic_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static int check_open(RingCore *self) {
    if (self->words == NULL) {
        PyErr_SetString(PyExc_ValueError, "the ring is closed");
        return -1;
    }
    return 0;
}

static unsigned long long align_up(unsigned long long n, unsigned long long to) {
    return (n + to - 1) / to * to;
}

/* Where the pool starts and how far apart its slots are; the segment's size. */
static unsigned long long pool_layout(unsigned long long cap, unsigned long long slots,
                                      unsigned long long slot_bytes,
                                      unsigned long long *pool_offset,
                                      unsigned long long *stride) {
    *pool_offset = align_up(HEADER + cap + 8 * slots, PAGE);
    *stride = align_up(slot_bytes, PAGE);
    return slots ? *pool_offset + slots * *stride : HEADER + cap;
}

static void put_header(unsigned char *at, uint32_t length, uint16_t kind, uint16_t meta_len,
                       uint64_t seq, double sent_at) {
    memcpy(at, &length, 4);
    memcpy(at + 4, &kind, 2);
    memcpy(at + 6, &meta_len, 2);
    memcpy(at + 8, &seq, 8);
    memcpy(at + 16, &sent_at, 8);
}

/* The header of the record at `offset`; 0 if its length cannot be a record's there
 * (a broken writer). */
static int get_header(RingCore *self, unsigned long long offset, uint32_t *length,
                      uint16_t *kind, uint16_t *meta_len, uint64_t *seq) {
    unsigned char *at = self->data + offset;
    memcpy(length, at, 4);
    memcpy(kind, at + 4, 2);
    memcpy(meta_len, at + 6, 2);
    memcpy(seq, at + 8, 8);
    return *length != 0 && *length % 8 == 0 && offset + *length <= self->cap;
}

static int RingCore_init(RingCore *self, PyObject *args, PyObject *kwds) {
    PyObject *segment;
    if (!PyArg_ParseTuple(args, "O", &segment))
        return -1;
    if (PyObject_GetBuffer(segment, &self->view, PyBUF_WRITABLE) < 0)
        return -1;
    if (self->view.len < HEADER + 64) {
        PyBuffer_Release(&self->view);
        PyErr_SetString(PyExc_ValueError, "segment too small for a ring");
        return -1;
    }
    self->words = (uint64_t *)self->view.buf;
    self->data = (unsigned char *)self->view.buf + HEADER;
    self->cap = self->words[W_CAP];
    self->slots = self->words[W_SLOTS];
    self->slot_bytes = self->words[W_SLOT_BYTES];
    unsigned long long size = pool_layout(self->cap, self->slots, self->slot_bytes,
                                          &self->pool_offset, &self->stride);
    if (self->cap == 0 || self->cap % 64 || self->slots > MAX_SLOTS
            || (self->slots && !self->slot_bytes) || size > (unsigned long long)self->view.len) {
        PyBuffer_Release(&self->view);
        self->words = NULL;
        PyErr_SetString(PyExc_ValueError, "segment header holds a bad capacity or pool");
        return -1;
    }
    self->states = (uint64_t *)(self->data + self->cap);
    self->pool = (unsigned char *)self->view.buf + self->pool_offset;
    self->head = self->published = LOAD_ACQ(&self->words[W_HEAD]);
    self->seq = self->words[W_SEQ];
    self->tail = LOAD_ACQ(&self->words[W_TAIL]);
    self->rpos = LOAD_ACQ(&self->words[W_RPOS]);
    self->expected = -1;
    self->leases = 0;
    self->bell = -1;
    return 0;
}

static void RingCore_dealloc(RingCore *self) {
    if (self->words != NULL)
        PyBuffer_Release(&self->view);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *RingCore_release(RingCore *self, PyObject *unused) {
    if (self->words != NULL) {
        self->words = NULL;
        self->data = NULL;
        self->states = NULL;
        self->pool = NULL;
        PyBuffer_Release(&self->view);
    }
    Py_RETURN_NONE;
}

/* -- writer ------------------------------------------------------------- */

/* Store the writer's head after the records (release), then, if the reader said
 * it is going to sleep, ring its bell. The fence orders the head store before the
 * load of `waiting` (the writer's half of the hand-shake). */
static void publish(RingCore *self) {
    if (self->head == self->published)
        return;
    self->published = self->head;
    STORE_REL(&self->words[W_HEAD], self->head);
    if (self->bell >= 0) {
        FENCE();
        if (__atomic_load_n(&self->words[W_WAITING], __ATOMIC_RELAXED)) {
            uint64_t one = 1;
            ssize_t done = write(self->bell, &one, 8);  /* EAGAIN: already rung enough */
            (void)done;
        }
    }
}

/* Room for `length` bytes at the writer's head: the record's start, or -1 when the
 * reader has not freed enough. A record that would straddle the end goes after a pad
 * record to the end, written and published as a step of its own: pad and record
 * together may exceed the capacity even in an empty ring, where each alone does not,
 * and then the record has room only once the reader has taken the pad (a writer
 * polling for room publishes nothing else meanwhile). Records staged before the pad
 * are published with it. */
static long long reserve(RingCore *self, unsigned long long length) {
    unsigned long long cap = self->cap, head = self->head;
    unsigned long long offset = head % cap;
    if (offset + length > cap) {
        unsigned long long pad = cap - offset;
        if (head + pad - self->tail > cap) {
            self->tail = LOAD_ACQ(&self->words[W_TAIL]);
            if (head + pad - self->tail > cap)
                return -1;
        }
        put_header(self->data + offset, (uint32_t)pad, K_PAD, 0, 0, 0.0);
        self->head = head = head + pad;
        STORE_RLX(&self->words[W_SEQ], self->seq);
        publish(self);
    }
    if (head + length - self->tail > cap) {
        self->tail = LOAD_ACQ(&self->words[W_TAIL]);
        if (head + length - self->tail > cap)
            return -1;
    }
    return (long long)head;
}

/* The lowest free slot, or -1. Large arrays travel in a pool of equal slots, not
 * in the ring itself, so that the writer keeps filling the same two or three slots
 * while the reader keeps up: they stay in cache, where cycling through a ring of
 * ten 1 MiB records does not (on this kind of host a 1 MiB copy runs at 10 GB/s
 * into 3 slots and 7.5 GB/s into 10). A slot is free again as soon as its view is
 * gone, in any order. The acquire load pairs with the reader's release store of 0
 * after its last read of the slot, so the copy that follows cannot overtake it. */
static long long take_slot(RingCore *self) {
    for (unsigned long long i = 0; i < self->slots; i++)
        if (LOAD_ACQ(&self->states[i]) == 0)
            return (long long)i;
    return -1;
}

/* room(length, slot) -> whether a record of `length` bytes (and, if `slot`, a free
 * slot) is there now (it may write and publish a pad to the end: see reserve). */
static PyObject *RingCore_room(RingCore *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "room takes (length, slot)");
        return NULL;
    }
    if (check_open(self) < 0)
        return NULL;
    unsigned long long length = PyLong_AsUnsignedLongLong(args[0]);
    int slot = PyObject_IsTrue(args[1]);
    if (PyErr_Occurred())
        return NULL;
    return PyBool_FromLong(reserve(self, length) >= 0 && (!slot || take_slot(self) >= 0));
}

static PyObject *RingCore_publish(RingCore *self, PyObject *unused) {
    if (check_open(self) < 0)
        return NULL;
    STORE_RLX(&self->words[W_SEQ], self->seq);
    publish(self);
    Py_RETURN_NONE;
}

/* Write an int64 or float64 record at the head: 1 written, 0 no room (nothing
 * changed), -1 not such a value (nothing changed), -2 error. */
static int put_scalar(RingCore *self, PyObject *value, double sent_at) {
    uint16_t kind;
    int64_t number = 0;
    double real = 0.0;
    if (PyLong_CheckExact(value)) {
        int overflow;
        number = PyLong_AsLongLongAndOverflow(value, &overflow);
        if (overflow)
            return -1;
        kind = K_INT;
    } else if (PyFloat_CheckExact(value)) {
        real = PyFloat_AS_DOUBLE(value);
        kind = K_FLOAT;
    } else {
        return -1;
    }
    if (check_open(self) < 0)
        return -2;
    long long start = reserve(self, SCALAR_LEN);
    if (start < 0)
        return 0;
    unsigned char *at = self->data + (unsigned long long)start % self->cap;
    put_header(at, SCALAR_LEN, kind, 0, self->seq, sent_at);
    if (kind == K_INT)
        memcpy(at + REC_HEAD, &number, 8);
    else
        memcpy(at + REC_HEAD, &real, 8);
    self->seq += 1;
    self->head = (unsigned long long)start + SCALAR_LEN;
    return 1;
}

/* put(value) -> 1, 0 or -1 as put_scalar; a written value is published at once. */
static PyObject *RingCore_put(RingCore *self, PyObject *value) {
    int done = put_scalar(self, value, monotonic_now());
    if (done == -2)
        return NULL;
    if (done == 1) {
        STORE_RLX(&self->words[W_SEQ], self->seq);
        publish(self);
    }
    return PyLong_FromLong(done);
}

/* stage(value, sent_at): as put, but leaves publishing to publish() (a batch
 * publishes once), and the write time is given (monotonic seconds). */
static PyObject *RingCore_stage(RingCore *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "stage takes (value, sent_at)");
        return NULL;
    }
    double sent_at = PyFloat_AsDouble(args[1]);
    if (sent_at == -1.0 && PyErr_Occurred())
        return NULL;
    int done = put_scalar(self, args[0], sent_at);
    return done == -2 ? NULL : PyLong_FromLong(done);
}

/* stage_record(kind, meta, payload, body, length, sent_at) -> 1 written, 0 no room:
 * one whole record (header, meta at 24, payload at `body`), unpublished, in one
 * call: for a large array this is the copy and nothing else. A K_SLOT record's
 * payload goes into a free slot instead, and its body holds the slot's index. */
static PyObject *RingCore_stage_record(RingCore *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 6 || !PyBytes_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError,
                        "stage_record takes (kind, meta bytes, payload, body, length, sent_at)");
        return NULL;
    }
    if (check_open(self) < 0)
        return NULL;
    long kind = PyLong_AsLong(args[0]);
    unsigned long long body = PyLong_AsUnsignedLongLong(args[3]);
    unsigned long long length = PyLong_AsUnsignedLongLong(args[4]);
    double sent_at = PyFloat_AsDouble(args[5]);
    if (PyErr_Occurred())
        return NULL;
    Py_ssize_t meta_len = PyBytes_GET_SIZE(args[1]);
    Py_buffer payload;
    if (PyObject_GetBuffer(args[2], &payload, PyBUF_SIMPLE) < 0)
        return NULL;
    PyObject *result = NULL;
    int in_slot = kind == K_SLOT;
    unsigned long long inline_len = in_slot ? 8 : (unsigned long long)payload.len;
    if (meta_len > 0xFFFF || body < REC_HEAD + (unsigned long long)meta_len || body % 8
            || length < body + inline_len || length % 64 || length > self->cap
            || (in_slot && (unsigned long long)payload.len > self->slot_bytes)) {
        PyErr_SetString(PyExc_ValueError, "stage_record: inconsistent record sizes");
        goto done;
    }
    long long slot = in_slot ? take_slot(self) : 0;
    long long start = slot < 0 ? -1 : reserve(self, length);
    if (start < 0) {
        result = PyLong_FromLong(0);
        goto done;
    }
    unsigned char *at = self->data + (unsigned long long)start % self->cap;
    put_header(at, (uint32_t)length, (uint16_t)kind, (uint16_t)meta_len, self->seq, sent_at);
    memcpy(at + REC_HEAD, PyBytes_AS_STRING(args[1]), (size_t)meta_len);
    if (in_slot) {
        uint64_t index = (uint64_t)slot;
        memcpy(self->pool + index * self->stride, payload.buf, (size_t)payload.len);
        /* Taken: only a reader restart reads this (see resume_reader); the head's
         * release store publishes it with the record. */
        STORE_RLX(&self->states[index], self->seq + 1);
        memcpy(at + body, &index, 8);
    } else {
        memcpy(at + body, payload.buf, (size_t)payload.len);
    }
    self->seq += 1;
    self->head = (unsigned long long)start + length;
    result = PyLong_FromLong(1);
done:
    PyBuffer_Release(&payload);
    return result;
}

/* claim_slot() -> the index of a free slot, now claimed for a value that is written
 * into it before its record is staged (a remote link's payload decrypted straight
 * into place: see ShmRing.claim), or -1 if none is free. A claimed slot is the
 * writer's until stage_claimed publishes it or unclaim_slot frees it; the reader
 * never sees it, and a reader restart leaves it alone (its state is above any seq). */
static PyObject *RingCore_claim_slot(RingCore *self, PyObject *unused) {
    if (check_open(self) < 0)
        return NULL;
    long long slot = take_slot(self);
    if (slot >= 0)
        STORE_RLX(&self->states[slot], CLAIMED);
    return PyLong_FromLongLong(slot);
}

/* unclaim_slot(index): a claimed slot whose value will never be staged (its tag
 * failed, or it was dropped) is free again. Nothing once the ring is closed. */
static PyObject *RingCore_unclaim_slot(RingCore *self, PyObject *arg) {
    unsigned long long index = PyLong_AsUnsignedLongLong(arg);
    if (PyErr_Occurred())
        return NULL;
    if (self->words != NULL && index < self->slots) {
        uint64_t claimed = CLAIMED;
        __atomic_compare_exchange_n(&self->states[index], &claimed, 0, 0, __ATOMIC_RELEASE,
                                    __ATOMIC_RELAXED);
    }
    Py_RETURN_NONE;
}

/* stage_claimed(index, meta, body, length, sent_at) -> 1 written, 0 no room: the
 * K_SLOT record of a claimed slot whose bytes are already in place, unpublished. No
 * copy: this is how a value decrypted into its slot lands. */
static PyObject *RingCore_stage_claimed(RingCore *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 5 || !PyBytes_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError,
                        "stage_claimed takes (index, meta bytes, body, length, sent_at)");
        return NULL;
    }
    if (check_open(self) < 0)
        return NULL;
    unsigned long long index = PyLong_AsUnsignedLongLong(args[0]);
    unsigned long long body = PyLong_AsUnsignedLongLong(args[2]);
    unsigned long long length = PyLong_AsUnsignedLongLong(args[3]);
    double sent_at = PyFloat_AsDouble(args[4]);
    if (PyErr_Occurred())
        return NULL;
    Py_ssize_t meta_len = PyBytes_GET_SIZE(args[1]);
    if (index >= self->slots || LOAD_ACQ(&self->states[index]) != CLAIMED) {
        PyErr_SetString(PyExc_ValueError, "stage_claimed: the slot is not claimed");
        return NULL;
    }
    if (meta_len > 0xFFFF || body < REC_HEAD + (unsigned long long)meta_len || body % 8
            || length < body + 8 || length % 64 || length > self->cap) {
        PyErr_SetString(PyExc_ValueError, "stage_claimed: inconsistent record sizes");
        return NULL;
    }
    long long start = reserve(self, length);
    if (start < 0)
        return PyLong_FromLong(0);
    unsigned char *at = self->data + (unsigned long long)start % self->cap;
    put_header(at, (uint32_t)length, K_SLOT, (uint16_t)meta_len, self->seq, sent_at);
    memcpy(at + REC_HEAD, PyBytes_AS_STRING(args[1]), (size_t)meta_len);
    uint64_t slot = (uint64_t)index;
    memcpy(at + body, &slot, 8);
    STORE_RLX(&self->states[index], self->seq + 1);   /* (as stage_record: see there) */
    self->seq += 1;
    self->head = (unsigned long long)start + length;
    return PyLong_FromLong(1);
}

/* Free the slots whose state (the seq of their record + 1) is in (above, upto]:
 * what a restarted reader or writer knows its dead predecessor left taken. */
static void free_slots(RingCore *self, uint64_t above, uint64_t upto) {
    for (unsigned long long i = 0; i < self->slots; i++) {
        uint64_t state = LOAD_ACQ(&self->states[i]);
        if (state > above && state <= upto)
            STORE_REL(&self->states[i], 0);
    }
}

/* The sequence number after the last record a dead writer published: the seq of
 * the last record before W_HEAD plus one. W_SEQ alone could overstate it: a writer
 * that died between its two publishing stores (W_SEQ, then W_HEAD) counted a batch
 * the reader will never see. Records from the reader's position up to W_HEAD stay
 * as they are while no writer runs; with none left, the reader has read everything
 * published and W_RSEQ says where that ended (stored before W_RPOS, which is
 * released after it). A record that makes no sense ends the walk at W_SEQ. */
static uint64_t last_published(RingCore *self) {
    unsigned long long head = LOAD_ACQ(&self->words[W_HEAD]);
    unsigned long long pos = LOAD_ACQ(&self->words[W_RPOS]);
    uint64_t published = __atomic_load_n(&self->words[W_RSEQ], __ATOMIC_RELAXED);
    if (head - pos > self->cap)
        return self->words[W_SEQ];
    while (pos != head) {
        uint32_t length;
        uint16_t kind, meta_len;
        uint64_t seq;
        if (!get_header(self, pos % self->cap, &length, &kind, &meta_len, &seq)
                || head - pos < length)
            return self->words[W_SEQ];
        if (kind != K_PAD)
            published = seq + 1;
        pos += length;
    }
    return published;
}

/* A writer (re)starts: slots a dead writer took for records it never published
 * are free again. Only one writer may be attached; the reader never takes slots,
 * so this cannot race with it. */
static PyObject *RingCore_resume_writer(RingCore *self, PyObject *unused) {
    if (check_open(self) < 0)
        return NULL;
    free_slots(self, last_published(self), UINT64_MAX);
    Py_RETURN_NONE;
}

/* -- reader ------------------------------------------------------------- */

/* free_slot(index): the reader is done with a slot (its last view is gone). A
 * release store: every read of the slot happens before the writer may reuse it. */
static PyObject *RingCore_free_slot(RingCore *self, PyObject *arg) {
    unsigned long long index = PyLong_AsUnsignedLongLong(arg);
    if (PyErr_Occurred())
        return NULL;
    if (self->words != NULL && index < self->slots)    /* closed: nothing to hand back */
        STORE_REL(&self->states[index], 0);
    Py_RETURN_NONE;
}

static PyObject *RingCore_slots_used(RingCore *self, PyObject *unused) {
    if (check_open(self) < 0)
        return NULL;
    long used = 0;
    for (unsigned long long i = 0; i < self->slots; i++)
        used += LOAD_ACQ(&self->states[i]) != 0;
    return PyLong_FromLong(used);
}

static int has_data(RingCore *self) {
    return LOAD_ACQ(&self->words[W_HEAD]) != self->rpos;
}

static PyObject *RingCore_has_data(RingCore *self, PyObject *unused) {
    if (self->words == NULL)
        Py_RETURN_FALSE;
    return PyBool_FromLong(has_data(self));
}

static PyObject *RingCore_store_tail(RingCore *self, PyObject *arg) {
    if (check_open(self) < 0)
        return NULL;
    unsigned long long tail = PyLong_AsUnsignedLongLong(arg);
    if (PyErr_Occurred())
        return NULL;
    if (tail > self->words[W_TAIL])
        STORE_REL(&self->words[W_TAIL], tail);
    Py_RETURN_NONE;
}

static PyObject *RingCore_counters(RingCore *self, PyObject *unused) {
    /* (head, tail, values written) as stored in the header, for statistics */
    if (check_open(self) < 0)
        return NULL;
    return Py_BuildValue("KKK", LOAD_ACQ(&self->words[W_HEAD]), LOAD_ACQ(&self->words[W_TAIL]),
                         __atomic_load_n(&self->words[W_SEQ], __ATOMIC_RELAXED));
}

static PyObject *RingCore_resume_reader(RingCore *self, PyObject *unused) {
    /* a new reader takes over: views held by a dead reader are gone, so are the
     * slots of records it read (seq below W_RSEQ); the writer marks a slot it takes
     * with a later seq, so this cannot free one on its way. It expects the record
     * after the last one read (W_RSEQ, 0 in a new ring): values the writer dropped
     * meanwhile are a gap it counts. */
    if (check_open(self) < 0)
        return NULL;
    self->rpos = LOAD_ACQ(&self->words[W_RPOS]);
    uint64_t rseq = __atomic_load_n(&self->words[W_RSEQ], __ATOMIC_RELAXED);
    self->expected = (long long)rseq;
    free_slots(self, 0, rseq);
    STORE_REL(&self->words[W_TAIL], self->rpos);
    Py_RETURN_NONE;
}

/* drain(limit, decode) -> (values, sent_at, gaps)
 * Ints, floats and pads are decoded here; any other record is handed to
 * decode(kind, offset, length, meta_len, start) in Python, which returns its value.
 * Without array views outstanding the tail follows the read position at once. */
static PyObject *RingCore_drain(RingCore *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "drain takes (limit, decode)");
        return NULL;
    }
    if (check_open(self) < 0)
        return NULL;
    Py_ssize_t limit = PyLong_AsSsize_t(args[0]);
    if (limit == -1 && PyErr_Occurred())
        return NULL;
    PyObject *decode = args[1];
    PyObject *values = PyList_New(0);
    if (values == NULL)
        return NULL;
    unsigned long long head = LOAD_ACQ(&self->words[W_HEAD]);
    unsigned long long rpos = self->rpos, start = rpos, cap = self->cap;
    long long expected = self->expected, gaps = 0;
    double sent_at = 0.0;
    while (rpos != head && PyList_GET_SIZE(values) < limit) {
        unsigned long long offset = rpos % cap;
        unsigned char *at = self->data + offset;
        uint32_t length;
        uint16_t kind, meta_len;
        uint64_t seq;
        if (!get_header(self, offset, &length, &kind, &meta_len, &seq)) {
            PyErr_Format(PyExc_RuntimeError,
                         "corrupt ring record at %llu (length %u): the writer misbehaved",
                         rpos, (unsigned)length);
            goto fail;
        }
        unsigned long long begin = rpos;
        rpos += length;
        if (kind == K_PAD)
            continue;
        memcpy(&sent_at, at + 16, 8);
        PyObject *item;
        if (kind == K_INT) {
            int64_t number;
            memcpy(&number, at + REC_HEAD, 8);
            item = PyLong_FromLongLong(number);
        } else if (kind == K_FLOAT) {
            double real;
            memcpy(&real, at + REC_HEAD, 8);
            item = PyFloat_FromDouble(real);
        } else {
            /* Python code may drop the last array view, whose callback moves the
             * tail up to rpos: everything before this record is consumed. */
            self->rpos = begin;
            item = PyObject_CallFunction(decode, "iKIHK", (int)kind, offset, (unsigned)length,
                                         meta_len, begin);
        }
        if (item == NULL)
            goto fail;
        if (self->words == NULL) {        /* released while Python ran: stop here */
            Py_DECREF(item);
            PyErr_SetString(PyExc_ValueError, "the ring was closed while draining");
            goto fail_closed;
        }
        int failed = PyList_Append(values, item);
        Py_DECREF(item);
        if (failed)
            goto fail;
        if (expected >= 0 && (long long)seq != expected)
            gaps += (long long)seq - expected;
        expected = (long long)seq + 1;
    }
    self->expected = expected;
    self->rpos = rpos;
    if (rpos != start) {
        if (expected >= 0)
            STORE_RLX(&self->words[W_RSEQ], (uint64_t)expected);
        STORE_REL(&self->words[W_RPOS], rpos);     /* after W_RSEQ: see last_published */
        if (self->leases == 0)
            STORE_REL(&self->words[W_TAIL], rpos);
    }
    return Py_BuildValue("NdL", values, sent_at, gaps);
fail:
    self->rpos = start;
fail_closed:
    Py_DECREF(values);
    return NULL;
}

/* -- the reader's sleep ------------------------------------------------- */

static void set_waiting(PyObject *rings, uint64_t flag) {
    Py_ssize_t n = PyList_GET_SIZE(rings);
    for (Py_ssize_t i = 0; i < n; i++) {
        RingCore *ring = (RingCore *)PyList_GET_ITEM(rings, i);
        if (ring->words != NULL)
            __atomic_store_n(&ring->words[W_WAITING], flag, __ATOMIC_RELAXED);
    }
}

static PyTypeObject RingCoreType;

/* sleep(bell, rings, timeout) -> bool: announce sleep on every ring, look once
 * more, then block on the doorbell (eventfd) without the GIL. True if woken or
 * data was already there. Rings closed meanwhile (by another thread, which needs
 * the GIL to do it) are skipped: ring memory is only touched while holding it. */
static PyObject *ringcore_sleep(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3 || !PyList_CheckExact(args[1])) {
        PyErr_SetString(PyExc_TypeError, "sleep takes (bell fd, list of RingCore, timeout)");
        return NULL;
    }
    int fd = PyLong_AsLong(args[0]);
    PyObject *rings = args[1];
    double timeout = PyFloat_AsDouble(args[2]);
    if (PyErr_Occurred())
        return NULL;
    Py_ssize_t n = PyList_GET_SIZE(rings);
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!PyObject_TypeCheck(PyList_GET_ITEM(rings, i), &RingCoreType)) {
            PyErr_SetString(PyExc_TypeError, "sleep: rings must be RingCore objects");
            return NULL;
        }
    }
    set_waiting(rings, 1);
    FENCE();     /* our waiting stores before the loads of head (Dekker) */
    int ready = 0;
    for (Py_ssize_t i = 0; i < n && !ready; i++) {
        RingCore *ring = (RingCore *)PyList_GET_ITEM(rings, i);
        ready = ring->words != NULL && has_data(ring);
    }
    if (!ready) {
        struct pollfd pfd = {.fd = fd, .events = POLLIN};
        int got;
        Py_BEGIN_ALLOW_THREADS
        got = poll(&pfd, 1, timeout < 0 ? -1 : (int)(timeout * 1000.0 + 0.999));
        if (got > 0) {
            uint64_t count;
            ssize_t done = read(fd, &count, 8);   /* EAGAIN: another waiter took it */
            (void)done;
        }
        Py_END_ALLOW_THREADS
        if (got < 0 && errno != EINTR)
            return PyErr_SetFromErrno(PyExc_OSError);
        ready = got > 0;
    }
    set_waiting(rings, 0);
    return PyBool_FromLong(ready);
}

static PyObject *ringcore_fence(PyObject *module, PyObject *unused) {
    FENCE();
    Py_RETURN_NONE;
}

static PyMemberDef RingCore_members[] = {
    {"capacity", T_ULONGLONG, offsetof(RingCore, cap), READONLY, "data bytes"},
    {"slots", T_ULONGLONG, offsetof(RingCore, slots), READONLY, "slots in the pool"},
    {"slot_bytes", T_ULONGLONG, offsetof(RingCore, slot_bytes), READONLY, "bytes a slot holds"},
    {"stride", T_ULONGLONG, offsetof(RingCore, stride), READONLY, "bytes between slots"},
    {"pool_offset", T_ULONGLONG, offsetof(RingCore, pool_offset), READONLY,
     "where the pool starts in the segment"},
    {"head", T_ULONGLONG, offsetof(RingCore, head), 0, "the writer's head"},
    {"seq", T_ULONGLONG, offsetof(RingCore, seq), 0, "the writer's next sequence number"},
    {"tail", T_ULONGLONG, offsetof(RingCore, tail), 0, "the tail the writer last saw"},
    {"rpos", T_ULONGLONG, offsetof(RingCore, rpos), 0, "the reader's position"},
    {"expected_seq", T_LONGLONG, offsetof(RingCore, expected), 0,
     "the sequence number the reader expects next (-1: any)"},
    {"leases", T_INT, offsetof(RingCore, leases), 0, "array views outstanding"},
    {"bell", T_INT, offsetof(RingCore, bell), 0, "the reader's eventfd, or -1"},
    {NULL}};

/* flush: set by the writer of a lossless link that is closing, read by its reader,
 * which then takes everything in the ring whether its input has room or not. A plain
 * flag: the records themselves are ordered by head as always. */
static PyObject *RingCore_get_flush(RingCore *self, void *closure) {
    if (self->words == NULL)
        Py_RETURN_FALSE;
    return PyBool_FromLong(__atomic_load_n(&self->words[W_FLUSH], __ATOMIC_RELAXED) != 0);
}

static int RingCore_set_flush(RingCore *self, PyObject *value, void *closure) {
    int flag = value == NULL ? 0 : PyObject_IsTrue(value);
    if (flag < 0)
        return -1;
    if (self->words != NULL)
        __atomic_store_n(&self->words[W_FLUSH], (uint64_t)flag, __ATOMIC_RELAXED);
    return 0;
}

static PyGetSetDef RingCore_getset[] = {
    {"flush", (getter)RingCore_get_flush, (setter)RingCore_set_flush,
     "the writer asks the reader to take everything now", NULL},
    {NULL}};

static PyMethodDef RingCore_methods[] = {
    {"release", (PyCFunction)RingCore_release, METH_NOARGS, "stop using the segment"},
    {"put", (PyCFunction)RingCore_put, METH_O, "write an int64 or float64 and publish it"},
    {"room", (PyCFunction)(void (*)(void))RingCore_room, METH_FASTCALL,
     "room for a record (and a slot) now?"},
    {"stage", (PyCFunction)(void (*)(void))RingCore_stage, METH_FASTCALL,
     "write an int64 or float64, unpublished"},
    {"publish", (PyCFunction)RingCore_publish, METH_NOARGS, "make records up to head visible"},
    {"stage_record", (PyCFunction)(void (*)(void))RingCore_stage_record, METH_FASTCALL,
     "write a whole record, unpublished"},
    {"claim_slot", (PyCFunction)RingCore_claim_slot, METH_NOARGS,
     "claim a free slot to write a value into before staging it"},
    {"unclaim_slot", (PyCFunction)RingCore_unclaim_slot, METH_O, "free a claimed slot"},
    {"stage_claimed", (PyCFunction)(void (*)(void))RingCore_stage_claimed, METH_FASTCALL,
     "the record of a claimed slot, unpublished"},
    {"has_data", (PyCFunction)RingCore_has_data, METH_NOARGS, "unread records?"},
    {"store_tail", (PyCFunction)RingCore_store_tail, METH_O, "hand bytes back to the writer"},
    {"resume_reader", (PyCFunction)RingCore_resume_reader, METH_NOARGS,
     "continue after a dead reader"},
    {"resume_writer", (PyCFunction)RingCore_resume_writer, METH_NOARGS,
     "continue after a dead writer"},
    {"free_slot", (PyCFunction)RingCore_free_slot, METH_O, "hand a slot back to the writer"},
    {"slots_used", (PyCFunction)RingCore_slots_used, METH_NOARGS, "slots taken"},
    {"counters", (PyCFunction)RingCore_counters, METH_NOARGS, "(head, tail, written)"},
    {"drain", (PyCFunction)(void (*)(void))RingCore_drain, METH_FASTCALL, "decode records"},
    {NULL}};

static PyTypeObject RingCoreType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "pb3a.transport._ringcore.RingCore",
    .tp_doc = "The C half of a ShmRing: header words, scalar writes, drain.",
    .tp_basicsize = sizeof(RingCore),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RingCore_init,
    .tp_dealloc = (destructor)RingCore_dealloc,
    .tp_members = RingCore_members,
    .tp_methods = RingCore_methods,
    .tp_getset = RingCore_getset,
};

/* segment_size(capacity, slots, slot_bytes) -> bytes a ring segment needs. */
static PyObject *ringcore_segment_size(PyObject *module, PyObject *args) {
    unsigned long long cap, slots, slot_bytes, pool_offset, stride;
    if (!PyArg_ParseTuple(args, "KKK", &cap, &slots, &slot_bytes))
        return NULL;
    if (slots > MAX_SLOTS || (slots && !slot_bytes)) {
        PyErr_Format(PyExc_ValueError, "a ring pool holds 1 to %d slots of at least 1 byte",
                     MAX_SLOTS);
        return NULL;
    }
    return PyLong_FromUnsignedLongLong(pool_layout(cap, slots, slot_bytes, &pool_offset, &stride));
}

static PyMethodDef module_methods[] = {
    {"segment_size", ringcore_segment_size, METH_VARARGS, "bytes a ring segment needs"},
    {"sleep", (PyCFunction)(void (*)(void))ringcore_sleep, METH_FASTCALL,
     "announce sleep on rings, look once more, block on the doorbell"},
    {"fence", ringcore_fence, METH_NOARGS, "a full memory barrier"},
    {NULL}};

static struct PyModuleDef ringcore_module = {
    PyModuleDef_HEAD_INIT, "_ringcore", "The C hot path of PB3A's shared-memory rings.", -1,
    module_methods};

PyMODINIT_FUNC PyInit__ringcore(void) {
    if (PyType_Ready(&RingCoreType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&ringcore_module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&RingCoreType);
    if (PyModule_AddObject(m, "RingCore", (PyObject *)&RingCoreType) < 0) {
        Py_DECREF(&RingCoreType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
