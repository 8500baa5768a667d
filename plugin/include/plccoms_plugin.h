/*
 * plccoms_plugin.h: the backend plugin ABI of plccoms, version 1.
 *
 * A section with SHM_NAME = <shared library> reaches its PLC through that
 * library instead of EPSNET. The library exports one function,
 *
 *     const plccoms_plugin_api *plccoms_plugin_entry(uint32_t abi_version);
 *
 * which the server calls with PLCCOMS_PLUGIN_ABI and which returns a table of
 * functions valid for the library's lifetime (NULL: this ABI version is not
 * supported). Every call but close returns a status:
 *
 *     PLCCOMS_OK (0)            done;
 *     1 .. 255                  the PLC refused this request with that EPSNET
 *                               error byte (0x02 unknown service, 0x03 not
 *                               activated, 0x04 blocked by password, 0x09 not
 *                               ready, 0x0C wrong parameters or out of range);
 *                               the link is fine;
 *     PLCCOMS_ERR_TIMEOUT (-1)  the PLC does not answer: the link is lost;
 *     PLCCOMS_ERR_IO (-2)       the link to the PLC failed: the link is lost;
 *     PLCCOMS_ERR_PROTOCOL (-3) the PLC answered something that makes no sense;
 *     PLCCOMS_ERR_UNSUPPORTED (-4) not supported by this plugin.
 *
 * and may write a message (UTF-8, NUL-terminated, at most
 * PLCCOMS_ERROR_LEN - 1 bytes) into err->text for the server's log. Any other
 * status is reported as a plugin error.
 *
 * The server's promises: it calls one handle from one thread at a time (a
 * thread of its own per section, never the thread serving clients), and
 * different handles possibly at the same time; every buffer it passes is
 * valid for the call only, with the length it says; paths are bytes (cp1250,
 * as clients send them), not NUL-terminated.
 *
 * The plugin's promises: it writes only within the buffers it is given and
 * reports how much it wrote; it returns. The server checks every length and
 * status it gets back and bounds every call by the section's timeout
 * (EPSTOUT + EPSTOUT + EPSTOUT_STEP): a call that takes longer is counted as
 * a timeout and the PLC as lost. A plugin that crashes stops the server (it
 * runs inside it): see "Plugins" in README.md.
 *
 * Memory areas: 'X' inputs, 'Y' outputs, 'S' system registers, 'R' user
 * registers; offsets in bytes; values little-endian as the PLC keeps them.
 * The server reads __PLC_RUN at S2.2 and __PF_CRC at S70 (DWORD) like every
 * other variable.
 */
#ifndef PLCCOMS_PLUGIN_H
#define PLCCOMS_PLUGIN_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define PLCCOMS_PLUGIN_ABI 1
#define PLCCOMS_PLUGIN_ENTRY "plccoms_plugin_entry"

#define PLCCOMS_OK 0
#define PLCCOMS_ERR_TIMEOUT (-1)
#define PLCCOMS_ERR_IO (-2)
#define PLCCOMS_ERR_PROTOCOL (-3)
#define PLCCOMS_ERR_UNSUPPORTED (-4)

#define PLCCOMS_ERROR_LEN 256
#define PLCCOMS_IDENT_LEN 64
#define PLCCOMS_NAME_LEN 255

/* A message from the plugin; zeroed by the server before each call. */
typedef struct plccoms_error {
    char text[PLCCOMS_ERROR_LEN];
} plccoms_error;

/* One key of the section, as the ini file gives it: SECTION (the section's
 * name), SHM_NAME, SHM_SOCKET, SHM_PORT, EPSTOUT, EPSTOUT_STEP (ms), and
 * IPADDR, EPSADDR, EPSPORT, SERIAL_DEVICE, SERIAL_SPEED when set. Keys are
 * upper case; both strings are NUL-terminated and valid during open only. */
typedef struct plccoms_key {
    const char *key;
    const char *value;
} plccoms_key;

/* A file's information, as the PLC keeps it: times are Windows FILETIME
 * (100 ns since 1601-01-01 UTC); attributes as FAT's (0x10 directory,
 * 0x20 archive, 0x01 read-only, 0x02 hidden, 0x04 system). */
typedef struct plccoms_file_info {
    uint64_t size;
    uint32_t attributes;
    uint32_t reserved; /* 0 */
    uint64_t created;
    uint64_t modified;
} plccoms_file_info;

typedef struct plccoms_dir_entry {
    plccoms_file_info info;
    uint32_t name_len; /* <= PLCCOMS_NAME_LEN */
    uint8_t name[PLCCOMS_NAME_LEN];
} plccoms_dir_entry;

typedef struct plccoms_plugin_api {
    uint32_t abi_version;    /* PLCCOMS_PLUGIN_ABI */
    uint32_t struct_size;    /* sizeof(plccoms_plugin_api) */
    uint32_t max_read_block; /* largest read or write asked of one call, 1 .. 65535; 0: 1230 */
    uint32_t max_file_block; /* largest file block asked of one call, 1 .. 65535; 0: 1150 */

    /* Connects to the PLC; *handle is passed to every other call (any value,
     * NULL included). Called again after the PLC was lost, on a new handle. */
    int32_t (*open)(const plccoms_key *keys, size_t key_count, void **handle,
                    plccoms_error *err);
    /* Releases a handle; no other call on it follows. */
    void (*close)(void *handle);
    /* The PLC's identification, e.g. "CP-1000    B 2.7 2.1": *len bytes
     * (<= cap, which is PLCCOMS_IDENT_LEN) written to buf, no NUL needed. */
    int32_t (*identify)(void *handle, char *buf, size_t cap, size_t *len,
                        plccoms_error *err);
    /* *run = 1 in RUN, 0 in HALT. */
    int32_t (*status)(void *handle, int32_t *run, plccoms_error *err);
    /* Reads len bytes of area from offset into buf; *got = the bytes written
     * (must be len when the status is PLCCOMS_OK). */
    int32_t (*read)(void *handle, char area, uint32_t offset, uint8_t *buf,
                    uint32_t len, uint32_t *got, plccoms_error *err);
    /* Writes len bytes to area at offset. */
    int32_t (*write)(void *handle, char area, uint32_t offset,
                     const uint8_t *data, uint32_t len, plccoms_error *err);
    /* byte = (byte & ~mask) | (value & mask), atomically in the PLC. */
    int32_t (*write_bits)(void *handle, char area, uint32_t offset,
                          uint8_t mask, uint8_t value, plccoms_error *err);

    /* The PLC's files: optional, NULL = file services not activated (the
     * server answers as a PLC without them). */
    int32_t (*file_info)(void *handle, const uint8_t *path, size_t path_len,
                         plccoms_file_info *info, plccoms_error *err);
    /* Up to cap bytes from offset; fewer (*len) only at the file's end. */
    int32_t (*file_read)(void *handle, const uint8_t *path, size_t path_len,
                         uint64_t offset, uint8_t *buf, uint32_t cap,
                         uint32_t *len, plccoms_error *err);
    /* Blocks follow each other from offset 0 (which starts the file anew);
     * the file appears when the block with last = 1 is written. */
    int32_t (*file_write)(void *handle, const uint8_t *path, size_t path_len,
                          uint64_t offset, const uint8_t *data, uint32_t len,
                          int32_t last, plccoms_error *err);
    int32_t (*file_write_info)(void *handle, const uint8_t *path,
                               size_t path_len, const plccoms_file_info *info,
                               plccoms_error *err);
    /* Entries of a directory from index start: *count (<= cap) written to
     * entries, *more = 1 when entries follow. */
    int32_t (*dir_list)(void *handle, const uint8_t *path, size_t path_len,
                        uint32_t start, plccoms_dir_entry *entries,
                        uint32_t cap, uint32_t *count, int32_t *more,
                        plccoms_error *err);
} plccoms_plugin_api;

const plccoms_plugin_api *plccoms_plugin_entry(uint32_t abi_version);

#ifdef __cplusplus
}
#endif

#endif /* PLCCOMS_PLUGIN_H */
