/* A window of a JPEG's rows and columns decoded by libjpeg-turbo, the rest not: rows above it
 * and below it are skipped (entropy-decoded only, jpeg_skip_scanlines: corrupt data there is
 * still an error) and columns beside it cropped (jpeg_crop_scanline). The window is widened by one iMCU (the
 * block of pixels one MCU covers) on every side: chroma upsampling treats the edge of what it
 * decodes as the image's edge, so only pixels that far inside are the full decode's (same
 * IDCT, upsampling and colour conversion; tests/unit/detector/test_jpeg_windows.py). Every
 * libjpeg warning is an error, as in simplejpeg's strict mode.
 *
 * What it earns, on the user's figure (python -m benchmarks.ab_jpeg_window --rounds 4 --per-round 8,
 * 2 cores, frames 30 ms apart, POST /v1/predict with a whole JPEG and 4 boxes, paired against the
 * same tree without it): 1920x1080 answered 1.14x sooner [1.06..1.17], 3840x2160 1.33x [1.30..1.37].
 *
 * Why C and not a library: PyTurboJPEG 2 needs libjpeg-turbo 3 (Debian 12 ships 2.1.5), and
 * PyTurboJPEG 1.8 over Debian's libturbojpeg0 crops losslessly to the same pixels at the same
 * speed (a 1080p frame's window: 6 ms against this decoder's 10 ms and the whole decode's 11 ms,
 * on a loaded machine) but reports libjpeg's warnings as Python warnings, which a threaded server
 * cannot turn into errors per call: of 300 JPEGs damaged outside the window, it decoded 146 that
 * the full decode refuses. The guarantee needs the whole image's pixels or a refusal. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <setjmp.h>
#include <stdio.h>
#include <jpeglib.h>

struct strict_errors {
    struct jpeg_error_mgr manager;
    jmp_buf escape;
    char message[JMSG_LENGTH_MAX];
};

static void fail(j_common_ptr info) {
    struct strict_errors *errors = (struct strict_errors *)info->err;
    (*info->err->format_message)(info, errors->message);
    longjmp(errors->escape, 1);
}

static void warn_as_error(j_common_ptr info, int level) {
    if (level < 0) fail(info); /* level >= 0: trace messages */
}

static PyObject *decode_window(PyObject *self, PyObject *args) {
    Py_buffer data;
    unsigned int x0, y0, x1, y1;
    int gray;
    if (!PyArg_ParseTuple(args, "y*IIIIp", &data, &x0, &y0, &x1, &y1, &gray)) return NULL;
    struct jpeg_decompress_struct info;
    struct strict_errors errors;
    PyObject *pixels = NULL;
    JDIMENSION x_start = 0, width = 0, y_start = 0, y_end = 0;
    volatile int failed = 0;
    info.err = jpeg_std_error(&errors.manager);
    errors.manager.error_exit = fail;
    errors.manager.emit_message = warn_as_error;
    errors.message[0] = '\0';
    jpeg_create_decompress(&info);
    if (setjmp(errors.escape)) {
        failed = 1;
    } else {
        jpeg_mem_src(&info, (const unsigned char *)data.buf, (unsigned long)data.len);
        jpeg_read_header(&info, TRUE);
        info.out_color_space = gray ? JCS_GRAYSCALE : JCS_EXT_BGR;
        jpeg_start_decompress(&info);
        if (x1 <= x0 || y1 <= y0 || x1 > info.output_width || y1 > info.output_height) {
            snprintf(errors.message, JMSG_LENGTH_MAX, "the window is outside the %ux%u image",
                     info.output_width, info.output_height);
            failed = 1;
        } else {
            unsigned int imcu_w = (unsigned int)info.max_h_samp_factor * DCTSIZE;
            unsigned int imcu_h = (unsigned int)info.max_v_samp_factor * DCTSIZE;
            x_start = x0 > imcu_w ? x0 - imcu_w : 0;
            width = (x1 + imcu_w < info.output_width ? x1 + imcu_w : info.output_width) - x_start;
            y_start = y0 > imcu_h ? y0 - imcu_h : 0;
            y_end = y1 + imcu_h < info.output_height ? y1 + imcu_h : info.output_height;
        }
    }
    if (!failed) {
        jpeg_crop_scanline(&info, &x_start, &width); /* to whole iMCU columns */
        size_t row_bytes = (size_t)width * info.output_components;
        pixels = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)(row_bytes * (y_end - y_start)));
        if (pixels == NULL) {
            jpeg_destroy_decompress(&info);
            PyBuffer_Release(&data);
            return NULL;
        }
        unsigned char *out = (unsigned char *)PyBytes_AS_STRING(pixels);
        Py_BEGIN_ALLOW_THREADS
        if (setjmp(errors.escape)) {
            failed = 1;
        } else {
            if (y_start > 0) jpeg_skip_scanlines(&info, y_start);
            while (info.output_scanline < y_end) {
                JSAMPROW row = out + (size_t)(info.output_scanline - y_start) * row_bytes;
                jpeg_read_scanlines(&info, &row, 1);
            }
            /* The rest entropy-decoded only (a skip to the very end would not decode it), and
             * the end marker read, so that corrupt data anywhere is still an error. */
            if (info.output_scanline + 1 < info.output_height)
                jpeg_skip_scanlines(&info, info.output_height - 1 - info.output_scanline);
            if (info.output_scanline < info.output_height) {
                JSAMPARRAY scratch = (*info.mem->alloc_sarray)((j_common_ptr)&info, JPOOL_IMAGE,
                                                               (JDIMENSION)row_bytes, 1);
                while (info.output_scanline < info.output_height) jpeg_read_scanlines(&info, scratch, 1);
            }
            jpeg_finish_decompress(&info);
        }
        Py_END_ALLOW_THREADS
    }
    jpeg_destroy_decompress(&info);
    PyBuffer_Release(&data);
    if (failed) {
        Py_XDECREF(pixels);
        PyErr_SetString(PyExc_ValueError, errors.message[0] ? errors.message : "the JPEG cannot be decoded");
        return NULL;
    }
    return Py_BuildValue("NIIII", pixels, x_start, y_start, width, y_end - y_start);
}

static PyMethodDef methods[] = {
    {"decode_window", decode_window, METH_VARARGS,
     "decode_window(data, x0, y0, x1, y1, gray) -> (pixels, x, y, width, height): a JPEG's\n"
     "pixels (BGR or gray, row-major bytes) in a window around columns x0..x1 - 1 and rows\n"
     "y0..y1 - 1, at (x, y) in the image, those within the full decode's; ValueError for a\n"
     "corrupt file or a window outside the image."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_jpeg_window", NULL, -1, methods};

PyMODINIT_FUNC PyInit__jpeg_window(void) {
    PyObject *created = PyModule_Create(&module);
    /* service/detector/images.py loads only a build of these sources: raise both together. */
    if (created != NULL && PyModule_AddIntConstant(created, "VERSION", 1) < 0) Py_CLEAR(created);
    return created;
}
