/* multi_lunar_lander._fast_calls: the per-call path of the Python vector env
 * (client_py/multi_lunar_lander/vector.py) as a CPython extension, so that a
 * step or a recv costs one call of the interpreter instead of a ctypes call
 * and the adapter's Python around it.
 *
 * It does not link the native library: vector.py hands it the addresses of
 * the library's functions and of the buffers the library reads and writes
 * (the actions' block, the results' offset, the event flag), so this module
 * holds no state of the engine's and calls nothing but what it is given.
 * client_cpp/CMakeLists.txt builds it for the stable ABI of CPython 3.9
 * (Py_LIMITED_API): one binary serves every CPython from 3.9 on.
 *
 * Records(offset_address, record_bytes, returned, info_keys, reuse,
 *         new_block, env_id_dtype)
 *   The records of a results block (vector.py's _Results).
 *   set_block(records, free_counts): a block's records (tuples: the returned
 *   arrays, the infos' arrays, env_ids, the record's owner) and the
 *   reference counts (as sys.getrefcount gives them) of a free record's.
 *   take(with_env_ids): the current record as step() returns it, (returned
 *   arrays..., infos dict, with infos["env_id"] as env_id_dtype when asked),
 *   then the offset moved on to a record nothing outside the block refers to
 *   (reuse), or new_block() called (it calls set_block) when every record is
 *   held, or after every take when reuse is off and new_block is not None.
 *
 * Call(function_address, handle, timeout_ms, events_address, records,
 *      actions_address=0, count=0, continuous=False, with_env_ids=False)
 *   call(): the library's function called with the GIL released: with an
 *   actions address int function(handle, actions, count, continuous,
 *   timeout_ms) (mll_vector_env_step), else int function(handle, timeout_ms)
 *   (mll_vector_env_recv). Returns records.take(with_env_ids) when it
 *   returned 0 and raised no event flag, else the code (an int) for the
 *   adapter's slower path. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stddef.h>
#include <stdint.h>

/* Points *slot at `value` (a new reference taken), dropping the old one. */
static void Replace(PyObject** slot, PyObject* value) {
  PyObject* old = *slot;
  Py_INCREF(value);
  *slot = value;
  Py_XDECREF(old);
}

/* ------------------------------------------------------------ Records */

typedef struct {
  PyObject_HEAD int64_t* offset;
  Py_ssize_t record_bytes;
  Py_ssize_t returned; /* How many of a record's members step() returns. */
  PyObject* info_keys; /* Tuple of str, one per infos member. */
  int reuse;
  PyObject* new_block;    /* Callable or None. */
  PyObject* env_id_dtype; /* What infos["env_id"] is made of env_ids as. */
  PyObject* records;      /* Tuple of record tuples. */
  Py_ssize_t* free_counts;
  Py_ssize_t members;
  Py_ssize_t current;
} Records;

static int Records_traverse(Records* self, visitproc visit, void* arg) {
  Py_VISIT(self->info_keys);
  Py_VISIT(self->new_block);
  Py_VISIT(self->env_id_dtype);
  Py_VISIT(self->records);
  return 0;
}

static int Records_clear(Records* self) {
  Py_CLEAR(self->info_keys);
  Py_CLEAR(self->new_block);
  Py_CLEAR(self->env_id_dtype);
  Py_CLEAR(self->records);
  return 0;
}

/* The end of a dealloc of this module's (heap) types: the memory freed and
 * the type's reference dropped. */
static void FreeObject(PyObject* self) {
  PyTypeObject* type = Py_TYPE(self);
  freefunc free_slot = (freefunc)PyType_GetSlot(type, Py_tp_free);
  free_slot(self);
  Py_DECREF(type);
}

static void Records_dealloc(Records* self) {
  PyObject_GC_UnTrack(self);
  Records_clear(self);
  PyMem_Free(self->free_counts);
  FreeObject((PyObject*)self);
}

static int Records_init(Records* self, PyObject* args, PyObject* kwargs) {
  unsigned long long offset_address = 0;
  Py_ssize_t record_bytes = 0, returned = 0;
  PyObject *info_keys = NULL, *new_block = NULL, *env_id_dtype = NULL;
  int reuse = 0;
  static char* keywords[] = {
      "offset_address", "record_bytes", "returned",     "info_keys",
      "reuse",          "new_block",    "env_id_dtype", NULL};
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "KnnO!pOO", keywords,
                                   &offset_address, &record_bytes, &returned,
                                   &PyTuple_Type, &info_keys, &reuse,
                                   &new_block, &env_id_dtype)) {
    return -1;
  }
  if (offset_address == 0 || record_bytes <= 0 || returned < 0) {
    PyErr_SetString(PyExc_ValueError,
                    "Records: offset_address must be non-zero, record_bytes "
                    "> 0, returned >= 0");
    return -1;
  }
  self->offset = (int64_t*)(uintptr_t)offset_address;
  self->record_bytes = record_bytes;
  self->returned = returned;
  self->reuse = reuse;
  Replace(&self->info_keys, info_keys);
  Replace(&self->new_block, new_block);
  Replace(&self->env_id_dtype, env_id_dtype);
  return 0;
}

static PyObject* Records_set_block(Records* self, PyObject* args) {
  PyObject *records = NULL, *counts = NULL;
  if (!PyArg_ParseTuple(args, "O!O!:set_block", &PyTuple_Type, &records,
                        &PyTuple_Type, &counts)) {
    return NULL;
  }
  const Py_ssize_t members = PyTuple_Size(counts);
  const Py_ssize_t needed =
      self->returned + PyTuple_Size(self->info_keys) + 2; /* env_ids, owner */
  if (PyTuple_Size(records) < 1 || members != needed) {
    PyErr_Format(PyExc_ValueError,
                 "set_block: %zd free counts for records of %zd members",
                 members, needed);
    return NULL;
  }
  for (Py_ssize_t i = 0; i < PyTuple_Size(records); ++i) {
    PyObject* record = PyTuple_GetItem(records, i);
    if (!PyTuple_Check(record) || PyTuple_Size(record) != members) {
      PyErr_Format(PyExc_ValueError,
                   "set_block: record %zd is not a tuple of %zd members", i,
                   members);
      return NULL;
    }
  }
  Py_ssize_t* free_counts = PyMem_Calloc((size_t)members, sizeof(Py_ssize_t));
  if (free_counts == NULL) return PyErr_NoMemory();
  for (Py_ssize_t i = 0; i < members; ++i) {
    free_counts[i] = PyLong_AsSsize_t(PyTuple_GetItem(counts, i));
    if (free_counts[i] == -1 && PyErr_Occurred()) {
      PyMem_Free(free_counts);
      return NULL;
    }
  }
  PyMem_Free(self->free_counts);
  self->free_counts = free_counts;
  self->members = members;
  Replace(&self->records, records);
  self->current = 0;
  *self->offset = 0;
  Py_RETURN_NONE;
}

/* Whether nothing but the block refers to record `index`'s members: their
 * counts are those of a free record. A count as sys.getrefcount sees it is
 * one more than Py_REFCNT (its argument). */
static int RecordIsFree(const Records* self, Py_ssize_t index) {
  PyObject* record = PyTuple_GetItem(self->records, index);
  for (Py_ssize_t i = 0; i < self->members; ++i) {
    if (Py_REFCNT(PyTuple_GetItem(record, i)) + 1 != self->free_counts[i]) {
      return 0;
    }
  }
  return 1;
}

/* Moves the offset on to the next free record, or to a new block. */
static int MoveOn(Records* self) {
  const Py_ssize_t count = PyTuple_Size(self->records);
  if (self->reuse) {
    for (Py_ssize_t step = 1; step < count; ++step) {
      const Py_ssize_t index = (self->current + step) % count;
      if (RecordIsFree(self, index)) {
        self->current = index;
        *self->offset = (int64_t)index * self->record_bytes;
        return 0;
      }
    }
  } else if (self->new_block == Py_None) {
    return 0; /* copy=False: one record, written by every call. */
  }
  PyObject* made = PyObject_CallObject(self->new_block, NULL);
  if (made == NULL) return -1;
  Py_DECREF(made);
  return 0;
}

static PyObject* Take(Records* self, int with_env_ids) {
  if (self->records == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "take: no block set");
    return NULL;
  }
  PyObject* record = PyTuple_GetItem(self->records, self->current);
  Py_INCREF(record); /* MoveOn may replace the block. */
  const Py_ssize_t infos = PyTuple_Size(self->info_keys);
  PyObject* result = PyTuple_New(self->returned + 1);
  PyObject* info = PyDict_New();
  if (result == NULL || info == NULL) goto failed;
  for (Py_ssize_t i = 0; i < self->returned; ++i) {
    PyObject* member = PyTuple_GetItem(record, i);
    Py_INCREF(member);
    PyTuple_SetItem(result, i, member);
  }
  for (Py_ssize_t i = 0; i < infos; ++i) {
    if (PyDict_SetItem(info, PyTuple_GetItem(self->info_keys, i),
                       PyTuple_GetItem(record, self->returned + i)) < 0) {
      goto failed;
    }
  }
  if (with_env_ids) {
    PyObject* ids =
        PyObject_CallMethod(PyTuple_GetItem(record, self->returned + infos),
                            "astype", "O", self->env_id_dtype);
    if (ids == NULL) goto failed;
    const int set = PyDict_SetItemString(info, "env_id", ids);
    Py_DECREF(ids);
    if (set < 0) goto failed;
  }
  PyTuple_SetItem(result, self->returned, info);
  info = NULL;
  if (MoveOn(self) < 0) goto failed;
  Py_DECREF(record);
  return result;
failed:
  Py_XDECREF(info);
  Py_XDECREF(result);
  Py_DECREF(record);
  return NULL;
}

static PyObject* Records_take(Records* self, PyObject* args) {
  int with_env_ids = 0;
  if (!PyArg_ParseTuple(args, "p:take", &with_env_ids)) return NULL;
  return Take(self, with_env_ids);
}

static PyObject* Records_get_current(Records* self, void* closure) {
  (void)closure;
  return PyLong_FromSsize_t(self->current);
}

static PyMethodDef Records_methods[] = {
    {"set_block", (PyCFunction)Records_set_block, METH_VARARGS,
     "set_block(records, free_counts): a new block's records."},
    {"take", (PyCFunction)Records_take, METH_VARARGS,
     "take(with_env_ids) -> (returned arrays..., infos): the current record, "
     "then the offset moved on; infos['env_id'] when with_env_ids."},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef Records_getset[] = {
    {"current", (getter)Records_get_current, NULL,
     "The index of the record the next call writes.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyType_Slot Records_slots[] = {
    {Py_tp_init, (void*)Records_init},
    {Py_tp_dealloc, (void*)Records_dealloc},
    {Py_tp_traverse, (void*)Records_traverse},
    {Py_tp_clear, (void*)Records_clear},
    {Py_tp_methods, Records_methods},
    {Py_tp_getset, Records_getset},
    {Py_tp_doc, "The records of a results block; see the module's doc."},
    {0, NULL},
};

static PyType_Spec Records_spec = {
    "multi_lunar_lander._fast_calls.Records", sizeof(Records), 0,
    Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,  Records_slots,
};

/* --------------------------------------------------------------- Call */

/* mll_vector_env_step and mll_vector_env_recv (vector_c_api.h). */
typedef int (*StepFunction)(void* handle, const void* actions, size_t count,
                            int continuous, int timeout_ms);
typedef int (*RecvFunction)(void* handle, int timeout_ms);

typedef struct {
  PyObject_HEAD void* function;
  void* handle;
  const void* actions; /* NULL: `function` is a RecvFunction. */
  size_t count;
  int continuous;
  int timeout_ms;
  int with_env_ids;
  const volatile int32_t* events;
  PyObject* records; /* A Records. */
} Call;

static int Call_traverse(Call* self, visitproc visit, void* arg) {
  Py_VISIT(self->records);
  return 0;
}

static int Call_clear(Call* self) {
  Py_CLEAR(self->records);
  return 0;
}

static void Call_dealloc(Call* self) {
  PyObject_GC_UnTrack(self);
  Call_clear(self);
  FreeObject((PyObject*)self);
}

static PyObject* RecordsType = NULL;

static int Call_init(Call* self, PyObject* args, PyObject* kwargs) {
  unsigned long long function = 0, handle = 0, events = 0, actions = 0;
  Py_ssize_t count = 0;
  int timeout_ms = 0, continuous = 0, with_env_ids = 0;
  PyObject* records = NULL;
  static char* keywords[] = {
      "function_address", "handle", "timeout_ms", "events_address", "records",
      "actions_address",  "count",  "continuous", "with_env_ids",   NULL};
  if (!PyArg_ParseTupleAndKeywords(
          args, kwargs, "KKiKO!|Knpp", keywords, &function, &handle,
          &timeout_ms, &events, (PyTypeObject*)RecordsType, &records, &actions,
          &count, &continuous, &with_env_ids)) {
    return -1;
  }
  if (function == 0 || handle == 0 || events == 0 || count < 0) {
    PyErr_SetString(PyExc_ValueError,
                    "Call: function_address, handle and events_address must "
                    "be non-zero, count >= 0");
    return -1;
  }
  self->function = (void*)(uintptr_t)function;
  self->handle = (void*)(uintptr_t)handle;
  self->actions = (const void*)(uintptr_t)actions;
  self->count = (size_t)count;
  self->continuous = continuous;
  self->timeout_ms = timeout_ms;
  self->with_env_ids = with_env_ids;
  self->events = (const volatile int32_t*)(uintptr_t)events;
  Replace(&self->records, records);
  return 0;
}

static PyObject* Call_call(Call* self, PyObject* args, PyObject* kwargs) {
  if (PyTuple_Size(args) != 0 || (kwargs != NULL && PyDict_Size(kwargs))) {
    PyErr_SetString(PyExc_TypeError, "Call() takes no arguments");
    return NULL;
  }
  int code;
  Py_BEGIN_ALLOW_THREADS if (self->actions != NULL) {
    code =
        ((StepFunction)self->function)(self->handle, self->actions, self->count,
                                       self->continuous, self->timeout_ms);
  }
  else {
    code = ((RecvFunction)self->function)(self->handle, self->timeout_ms);
  }
  Py_END_ALLOW_THREADS if (code != 0 ||
                           *self->events != 0) return PyLong_FromLong(code);
  return Take((Records*)self->records, self->with_env_ids);
}

static PyType_Slot Call_slots[] = {
    {Py_tp_init, (void*)Call_init},
    {Py_tp_dealloc, (void*)Call_dealloc},
    {Py_tp_traverse, (void*)Call_traverse},
    {Py_tp_clear, (void*)Call_clear},
    {Py_tp_call, (void*)Call_call},
    {Py_tp_doc, "A step call of the library; see the module's doc."},
    {0, NULL},
};

static PyType_Spec Call_spec = {
    "multi_lunar_lander._fast_calls.Call",   sizeof(Call), 0,
    Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC, Call_slots,
};

/* ------------------------------------------------------------- module */

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "_fast_calls",
    .m_doc = "The Python vector env's per-call path; see the source's comment.",
    .m_size = -1,
};

PyMODINIT_FUNC PyInit__fast_calls(void) {
  PyObject* m = PyModule_Create(&module);
  if (m == NULL) return NULL;
  RecordsType = PyType_FromSpec(&Records_spec);
  PyObject* call_type = PyType_FromSpec(&Call_spec);
  if (RecordsType == NULL || call_type == NULL ||
      PyModule_AddObject(m, "Records", RecordsType) < 0) {
    Py_XDECREF(call_type);
    Py_DECREF(m);
    return NULL;
  }
  Py_INCREF(
      RecordsType); /* The module took one reference; Call_init uses it. */
  if (PyModule_AddObject(m, "Call", call_type) < 0) {
    Py_DECREF(call_type);
    Py_DECREF(m);
    return NULL;
  }
  return m;
}
