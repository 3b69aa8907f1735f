/* A window of a JPEG frame, decoded by libjpeg-turbo alone (manus_core/jpeg_window.py loads this).
 *
 * The rows above the window are entropy-decoded and not transformed (jpeg_skip_scanlines), only
 * the window's columns, widened to whole iMCUs, are transformed and converted (jpeg_crop_scanline),
 * and the rows below it are not decoded at all: the same pixels as a whole decode's, for a
 * fraction of its cost. Except at the decoded columns' outer edges, where the chroma's smooth
 * upsampling has no neighbour outside the crop: one column more is decoded on each side and not
 * counted as decoded. Built by `make` (the Makefile's setup); plain C, called through ctypes. */

#include <setjmp.h>
#include <stdio.h>
#include <string.h>
#include <jpeglib.h>

struct failure {
    struct jpeg_error_mgr base;
    jmp_buf back;
};

static void fail(j_common_ptr info) {
    longjmp(((struct failure *)info->err)->back, 1);
}

static void quiet(j_common_ptr info, int level) {
    (void)info; (void)level;   /* warnings (a bit flipped on the link) are decoded through, as libjpeg does */
}

/* Decode rows [y, y + h) and at least columns [x, x + w) of a baseline JPEG as BGR into their
 * place in `out`, a whole frame's buffer (out_height rows of out_width pixels, BGR, no padding).
 * *got_x, *got_w: the columns decoded as a whole decode has them (x and w widened to the iMCU
 * grid); one column on each side of those may be written too, no other pixel of `out` is.
 * Returns 0, or -1 with libjpeg's message (or the window's or buffer's fault). */
int mc_decode_window(const unsigned char *data, unsigned long size, int x, int y, int w, int h,
                     unsigned char *out, int out_width, int out_height, int *got_x, int *got_w,
                     char *message, int message_size) {
    struct jpeg_decompress_struct info;
    struct failure err;
    info.err = jpeg_std_error(&err.base);
    err.base.error_exit = fail;
    err.base.emit_message = quiet;
    if (setjmp(err.back)) {
        (*info.err->format_message)((j_common_ptr)&info, message);
        jpeg_destroy_decompress(&info);
        return -1;
    }
    jpeg_create_decompress(&info);
    jpeg_mem_src(&info, data, size);
    jpeg_read_header(&info, TRUE);
    info.out_color_space = JCS_EXT_BGR;
    jpeg_start_decompress(&info);
    if (info.output_width != (JDIMENSION)out_width || info.output_height != (JDIMENSION)out_height) {
        snprintf(message, message_size, "a %ux%u frame for a %dx%d buffer",
                 info.output_width, info.output_height, out_width, out_height);
        jpeg_destroy_decompress(&info);
        return -1;
    }
    if (x < 0 || y < 0 || w <= 0 || h <= 0 || (JDIMENSION)(x + w) > info.output_width ||
        (JDIMENSION)(y + h) > info.output_height) {
        snprintf(message, message_size, "window %dx%d at (%d, %d) outside the %ux%u frame",
                 w, h, x, y, info.output_width, info.output_height);
        jpeg_destroy_decompress(&info);
        return -1;
    }
    JDIMENSION frame_width = info.output_width;   /* jpeg_crop_scanline sets output_width to the crop's */
    JDIMENSION left = x > 0 ? (JDIMENSION)x - 1 : 0;
    JDIMENSION width = (JDIMENSION)(x + w) - left + ((JDIMENSION)(x + w) < frame_width);
    jpeg_crop_scanline(&info, &left, &width);
    if (y > 0)
        jpeg_skip_scanlines(&info, (JDIMENSION)y);
    for (int row = 0; row < h; row++) {
        JSAMPROW line = out + ((unsigned long)(y + row) * frame_width + left) * 3;
        jpeg_read_scanlines(&info, &line, 1);
    }
    /* the rows below are not needed: destroying the decompressor leaves them undecoded */
    jpeg_destroy_decompress(&info);
    /* the crop's outer columns are exact only where they are the frame's own edges */
    int inner_left = left > 0, inner_right = left + width < frame_width;
    *got_x = (int)left + inner_left;
    *got_w = (int)width - inner_left - inner_right;
    return 0;
}
